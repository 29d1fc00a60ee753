//! Recovered delivery ([`crate::Delivery::Recovered`]): the maps' inputs, which a subscriber must
//! not miss even while its link moves to another router.
//!
//! Built on zenoh-ext's advanced publisher and subscriber: the publisher numbers its samples
//! and keeps the last [`CACHE_SAMPLES`] in a cache others may query; a subscriber that receives
//! a sample whose number skips one holds it back, asks the publisher's cache for the ones
//! between, and delivers all of them in order. Only a gap seen in the numbers is asked for
//! (no heartbeats, no periodic queries): a planner that joins late must not be handed the
//! cache's history, which its snapshot already holds. A sample the cache no longer holds, or a
//! publisher that cannot be reached within [`QUERY_TIMEOUT`], is counted in
//! [`crate::DropCounters::unrecovered`] and the held samples are delivered without it.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use zenoh::bytes::ZBytes;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::sample::Sample;
use zenoh::Session;
use zenoh_ext::{
    AdvancedPublisher, AdvancedPublisherBuilderExt, AdvancedSubscriber,
    AdvancedSubscriberBuilderExt, CacheConfig, MissDetectionConfig, RecoveryConfig,
};

use crate::DropCounters;

/// Samples a recovered publisher keeps for subscribers that missed some. A trolley's clouds
/// come every second or two, and a client moves to the other router within about two seconds
/// (its lease and reconnection): eight is several failovers' worth.
pub const CACHE_SAMPLES: usize = 8;

/// How long a subscriber waits for a publisher's cache to answer before it delivers what it
/// holds back without the missing samples.
pub const QUERY_TIMEOUT: Duration = Duration::from_secs(2);

/// A Zenoh publisher, plain or recovered.
pub(crate) enum ZenohPublisher {
    Plain(zenoh::pubsub::Publisher<'static>),
    Recovered(AdvancedPublisher<'static>),
}

impl ZenohPublisher {
    pub(crate) async fn declare(
        session: &Session,
        key: &str,
        (congestion, priority): (CongestionControl, Priority),
        recovered: bool,
    ) -> zenoh::Result<Self> {
        let builder = session
            .declare_publisher(key.to_owned())
            .congestion_control(congestion)
            .priority(priority);
        Ok(match recovered {
            false => Self::Plain(builder.await?),
            true => Self::Recovered(
                builder
                    .cache(CacheConfig::default().max_samples(CACHE_SAMPLES))
                    .sample_miss_detection(MissDetectionConfig::default())
                    .await?,
            ),
        })
    }

    pub(crate) async fn put(&self, bytes: Vec<u8>) -> zenoh::Result<()> {
        let payload = ZBytes::from(bytes);
        match self {
            Self::Plain(p) => p.put(payload).await,
            Self::Recovered(p) => p.put(payload).await,
        }
    }
}

/// A Zenoh subscriber, plain or recovered; kept only to stay declared.
pub(crate) enum ZenohSubscriber {
    Plain(#[allow(dead_code)] zenoh::pubsub::Subscriber<()>),
    Recovered(#[allow(dead_code)] AdvancedSubscriber<()>),
}

impl ZenohSubscriber {
    pub(crate) async fn declare(
        session: &Session,
        key_expr: &str,
        recovered: bool,
        counters: Arc<DropCounters>,
        callback: impl Fn(Sample) + Send + Sync + 'static,
    ) -> zenoh::Result<Self> {
        let builder = session.declare_subscriber(key_expr.to_owned());
        if !recovered {
            return Ok(Self::Plain(builder.callback(callback).await?));
        }
        let subscriber = builder
            .callback(callback)
            .recovery(RecoveryConfig::<true>::default())
            .query_timeout(QUERY_TIMEOUT)
            .await?;
        let key = key_expr.to_owned();
        subscriber
            .sample_miss_listener()
            .callback(move |miss| {
                let n = counters
                    .unrecovered
                    .fetch_add(u64::from(miss.nb()), Ordering::Relaxed);
                tracing::warn!(%key, missed = miss.nb(), before = n, "samples missed and not recovered");
            })
            .background()
            .await?;
        Ok(Self::Recovered(subscriber))
    }
}
