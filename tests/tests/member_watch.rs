//! Membership over real Zenoh: every leave is checked again a second later (a leave can be stale
//! with two routers), and a member that really left is not brought back by the check.

use std::time::Duration;

use glasshouse_bus::{declare_alive, BusArgs, MemberEvent, MemberWatch, LEAVE_RECHECK_AFTER};
use glasshouse_proto::keys::MemberKind;
use glasshouse_tests::{client, free_port, within};

/// No event for twice the recheck delay and a second more: the check of a leave has come and
/// gone.
async fn assert_quiet(watch: &mut MemberWatch, what: &str) {
    let window = 2 * LEAVE_RECHECK_AFTER + Duration::from_secs(1);
    if let Ok(event) = tokio::time::timeout(window, watch.recv()).await {
        panic!("{what}: unexpected {event:?}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_member_that_left_is_not_brought_back_by_the_recheck() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let _router = glasshouse_bus::open(&BusArgs::router(&endpoint))
        .await
        .expect("router");
    let watcher = client(&endpoint).await;
    let mut watch = MemberWatch::declare(&watcher, MemberKind::Trolley)
        .await
        .expect("watch");
    let left = |id: &str| Some(MemberEvent::Left(id.into()));

    // A token undeclared.
    let member = client(&endpoint).await;
    let token = join(&mut watch, &member, "t1").await;
    token.undeclare().await.expect("undeclare");
    assert_eq!(within(10, "t1 leaves", watch.recv()).await, left("t1"));
    assert_quiet(&mut watch, "after t1's undeclaration").await;

    // A session closed with its token declared.
    let other = client(&endpoint).await;
    let _token = join(&mut watch, &other, "t2").await;
    other.close().await.expect("close");
    assert_eq!(within(10, "t2 leaves", watch.recv()).await, left("t2"));
    assert_quiet(&mut watch, "after t2's session closed").await;

    // Back again: a join as before.
    let _again = join(&mut watch, &member, "t1").await;
}

/// Declares trolley `id` alive on `session` and waits for `watch` to see it join.
async fn join(
    watch: &mut MemberWatch,
    session: &zenoh::Session,
    id: &str,
) -> zenoh::liveliness::LivelinessToken {
    let token = declare_alive(session, MemberKind::Trolley, id)
        .await
        .expect("token");
    let event = within(10, "the member joins", watch.recv()).await;
    assert_eq!(event, Some(MemberEvent::Joined(id.into())));
    token
}
