//! A deployment secured by `glasshouse secure`: the fleet runs over mutual TLS through a router
//! with the generated ACL, while a rogue tries what its certificate does not allow.
//!
//! A refused message is shown by a control: the rogue sends the forbidden message and then an
//! allowed one on the same link and priority, so had the first passed the router it would reach
//! the observer first; the observer sees the control and not the forbidden one.

use std::path::{Path, PathBuf};
use std::process::Command;

use glasshouse_bus::{ask, AskError, BusArgs};
use glasshouse_dashboard::DashboardSettings;
use glasshouse_edge::EdgeEvent;
use glasshouse_planner::PlannerSettings;
use glasshouse_proto::{keys, MapSnapshot};
use glasshouse_tests::procs::{bin_dir, build_binaries};
use glasshouse_tests::{free_port, open, test_edge_config, within, FleetSessions, Pipeline};
use serde_json::Value;
use tokio::sync::mpsc::{unbounded_channel, UnboundedReceiver, UnboundedSender};
use zenoh::qos::CongestionControl;
use zenoh::Session;

fn glasshouse(args: &[&str]) {
    let out = Command::new(bin_dir().join("glasshouse"))
        .args(args)
        .output()
        .expect("glasshouse runs");
    assert!(
        out.status.success(),
        "glasshouse {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn config_of(pki: &Path, name: &str) -> PathBuf {
    pki.join(format!("{name}.json5"))
}

fn identity(pki: &Path, name: &str) -> BusArgs {
    BusArgs {
        zenoh_config: Some(config_of(pki, name)),
        ..BusArgs::default()
    }
}

/// A client config derived from `base`'s (its TLS section changed by `edit`) that tries to
/// connect once and fails instead of retrying.
fn one_try_config(dir: &Path, base: &Path, name: &str, edit: impl FnOnce(&mut Value)) -> BusArgs {
    let text = std::fs::read_to_string(base).expect("config");
    let mut config: Value = json5::from_str(&text).expect("JSON5 config");
    config["connect"]["timeout_ms"] = 0.into();
    config["connect"]["exit_on_failure"] = true.into();
    edit(&mut config["transport"]["link"]["tls"]);
    let path = dir.join(format!("{name}.json5"));
    std::fs::write(&path, config.to_string()).expect("write config");
    BusArgs {
        zenoh_config: Some(path),
        ..BusArgs::default()
    }
}

/// Opening a session from `args` must fail.
async fn refused_open(args: &BusArgs, what: &str) {
    let outcome = within(10, what, glasshouse_bus::open(args)).await;
    assert!(outcome.is_err(), "{what} was let in");
}

/// What an observer session receives, in arrival order: (key, payload).
struct Observer {
    rx: UnboundedReceiver<(String, Vec<u8>)>,
    _subscribers: Vec<zenoh::pubsub::Subscriber<()>>,
}

fn forward(
    tx: &UnboundedSender<(String, Vec<u8>)>,
) -> impl Fn(zenoh::sample::Sample) + Send + Sync + 'static {
    let tx = tx.clone();
    move |sample| {
        let key = sample.key_expr().as_str().to_owned();
        let _ = tx.send((key, sample.payload().to_bytes().into_owned()));
    }
}

impl Observer {
    /// Subscribes to `data` keys and to the liveliness of `alive` keys, into one queue.
    async fn declare(session: &Session, data: &[&str], alive: &[&str]) -> Observer {
        let (tx, rx) = unbounded_channel();
        let mut subscribers = Vec::new();
        for key in data {
            let sub = session
                .declare_subscriber(*key)
                .callback(forward(&tx))
                .await;
            subscribers.push(sub.expect("observer subscribes"));
        }
        for key in alive {
            let sub = session
                .liveliness()
                .declare_subscriber(*key)
                .callback(forward(&tx))
                .await;
            subscribers.push(sub.expect("observer watches liveliness"));
        }
        Observer {
            rx,
            _subscribers: subscribers,
        }
    }

    /// Waits for the first sample `control` accepts; true when `forbidden` accepted one before.
    async fn seen_before(
        &mut self,
        forbidden: impl Fn(&str, &[u8]) -> bool,
        control: impl Fn(&str, &[u8]) -> bool,
    ) -> bool {
        let mut seen = false;
        within(20, "the control message", async {
            while let Some((key, payload)) = self.rx.recv().await {
                if control(&key, &payload) {
                    return;
                }
                seen |= forbidden(&key, &payload);
            }
            panic!("observer closed");
        })
        .await;
        seen
    }
}

async fn put(session: &Session, key: &str, payload: &str) {
    session
        .put(key, payload.as_bytes().to_vec())
        .congestion_control(CongestionControl::Block)
        .await
        .expect("put returns (a refused put is dropped by the router, not at the sender)");
}

/// `session` puts a tagged payload on `key`, then a control on `control_key`; true when the
/// observer saw the first before the control.
async fn put_passes(
    session: &Session,
    observer: &mut Observer,
    key: &str,
    control_key: &str,
) -> bool {
    let (rogue, control) = (format!("rogue {key}"), format!("control {key}"));
    put(session, key, &rogue).await;
    put(session, control_key, &control).await;
    observer
        .seen_before(|_, p| p == rogue.as_bytes(), |_, p| p == control.as_bytes())
        .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn only_the_roster_may_do_its_part() {
    build_binaries();
    let dir = std::env::temp_dir().join(format!("glasshouse-secure-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (pki, other) = (dir.join("pki"), dir.join("other"));
    let port = free_port();
    let endpoint = format!("tls/127.0.0.1:{port}");
    let out = pki.to_string_lossy().into_owned();
    glasshouse(&[
        "secure",
        "init",
        "--out",
        &out,
        "--trolleys",
        "t1",
        "--planners",
        "p1,p2",
        "--detectors",
        "d1",
        "--dashboards",
        "web1",
        "--router-endpoint",
        &endpoint,
    ]);
    // The rogue's identity comes later, signed by the same CA.
    glasshouse(&["secure", "issue", "--out", &out, "--trolley", "t2"]);
    let other_out = other.to_string_lossy().into_owned();
    glasshouse(&[
        "secure",
        "init",
        "--out",
        &other_out,
        "--trolleys",
        "t1",
        "--router-endpoint",
        &endpoint,
    ]);

    let sessions = FleetSessions {
        endpoint: endpoint.clone(),
        router: BusArgs {
            listen: vec![endpoint.clone()],
            ..identity(&pki, "router")
        },
        dashboard: identity(&pki, "dashboard-web1"),
        detector: identity(&pki, "detector-d1"),
        planner: identity(&pki, "planner-p1"),
        edge: identity(&pki, "trolley-t1"),
    };
    let mut pipeline = Pipeline::start_services_on(
        sessions,
        DashboardSettings::default(),
        PlannerSettings::new("p1"),
    )
    .await;
    let web1 = open(&identity(&pki, "dashboard-web1")).await;
    let p2 = open(&identity(&pki, "planner-p2")).await;
    let t2 = open(&identity(&pki, "trolley-t2")).await;
    let mut watch_data = Observer::declare(
        &web1,
        &[
            "gh/trolley/*/rgbd",
            "gh/trolley/*/views",
            "gh/trolley/*/roi",
            "gh/trolley/*/status",
            "gh/trolley/*/fruits",
        ],
        &[],
    )
    .await;
    let mut watch_alive =
        Observer::declare(&p2, &[], &["gh/alive/planner/*", "gh/alive/trolley/*"]).await;
    pipeline.start_edge(test_edge_config(4)).await;

    // Sessions without a certificate of this CA cannot open.
    let t2_config = config_of(&pki, "trolley-t2");
    let same = one_try_config(&dir, &t2_config, "same", |_| {});
    within(10, "a one-try session", glasshouse_bus::open(&same))
        .await
        .expect("the one-try config itself connects")
        .close()
        .await
        .expect("close");
    let no_cert = one_try_config(&dir, &t2_config, "no-cert", |tls| {
        tls["enable_mtls"] = false.into();
        tls.as_object_mut().map(|t| t.remove("connect_private_key"));
        tls.as_object_mut().map(|t| t.remove("connect_certificate"));
    });
    refused_open(&no_cert, "a session without a certificate").await;
    let foreign = one_try_config(&dir, &t2_config, "foreign", |tls| {
        tls["connect_private_key"] = other
            .join("trolley-t1.key")
            .to_string_lossy()
            .into_owned()
            .into();
        tls["connect_certificate"] = other
            .join("trolley-t1.pem")
            .to_string_lossy()
            .into_owned()
            .into();
    });
    refused_open(&foreign, "a certificate of another CA").await;

    // The method sees a message that is allowed (a planner writes views and fruits).
    assert!(
        put_passes(
            &p2,
            &mut watch_data,
            "gh/trolley/t9/views",
            "gh/trolley/t9/fruits"
        )
        .await
    );
    // A valid trolley-t2 identity: not t1's keys, no views or clouds, not even its own.
    for (key, control) in [
        ("gh/trolley/t1/rgbd", "gh/trolley/t2/rgbd"),
        ("gh/trolley/t1/views", "gh/trolley/t2/status"),
        ("gh/trolley/t2/views", "gh/trolley/t2/status"),
        ("gh/trolley/t2/roi", "gh/trolley/t2/status"),
        ("gh/trolley/t1/status", "gh/trolley/t2/status"),
    ] {
        assert!(
            !put_passes(&t2, &mut watch_data, key, control).await,
            "trolley-t2 put on {key}"
        );
    }
    // Nor a planner's liveliness token.
    let fake_planner = t2
        .liveliness()
        .declare_token("gh/alive/planner/t2")
        .await
        .expect("declared");
    let own_token = t2
        .liveliness()
        .declare_token("gh/alive/trolley/t2")
        .await
        .expect("declared");
    let planner_token_seen = watch_alive
        .seen_before(
            |k, _| k == "gh/alive/planner/t2",
            |k, _| k == "gh/alive/trolley/t2",
        )
        .await;
    assert!(
        !planner_token_seen,
        "a trolley identity announced itself as a planner"
    );

    // Snapshots: a planner is answered (a map or a refusal); a trolley or dashboard gets nothing.
    let snapshot = keys::planner_snapshot("p1", "t1").expect("key");
    let asked = ask::<MapSnapshot>(&p2, &snapshot, std::time::Duration::from_secs(10)).await;
    assert!(
        !matches!(asked, Err(AskError::NoReply(_))),
        "planner p2 got no answer: {asked:?}"
    );
    for rogue in [&t2, &web1] {
        let asked = ask::<MapSnapshot>(rogue, &snapshot, std::time::Duration::from_secs(10)).await;
        assert!(
            matches!(asked, Err(AskError::NoReply(_))),
            "a snapshot query was answered: {asked:?}"
        );
    }

    let events = pipeline.run_to_end(240).await;
    let views = events
        .iter()
        .filter(|e| matches!(e, EdgeEvent::ViewDone { .. }))
        .count();
    assert!(views >= 3, "only {views} views executed: {events:?}");
    let fleet = pipeline.fleet.lock().expect("fleet state").clone();
    let trolley = fleet
        .trolleys
        .get("t1")
        .expect("the dashboard saw trolley t1");
    assert!(!trolley.fruits.is_empty(), "no fruit found");
    assert!(!fleet.trolleys.contains_key("t2") || fleet.trolleys["t2"].views_messages == 0);
    drop((fake_planner, own_token));
    for session in [web1, p2, t2] {
        let _ = session.close().await;
    }
    pipeline.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}
