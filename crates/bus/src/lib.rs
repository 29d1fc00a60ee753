//! The Zenoh glue: session config, typed publishers and subscribers, liveliness.
//!
//! This is the only library that touches Zenoh. Every binary shares the same session flags
//! ([`BusArgs`]: `--zenoh-config FILE`, `-e/--connect`, `-l/--listen`, `--mode`), so a user of one
//! binary knows them all. Multicast scouting is off unless a config file turns it on: endpoints are
//! explicit.
//!
//! Publishers and subscribers are typed by their key: [`Publisher<M>`] and [`Subscriber<M>`] are
//! declared from a [`Key<M>`] and carry only `M`; [`AnySubscriber`] receives every kind as a
//! [`Message`] (the dashboard); [`ask`] and [`Responder`] are typed the same way.
//!
//! Publishing never awaits the network on the caller's path: [`Publisher::publish`] encodes and
//! queues, and a task per publisher drains the queue into Zenoh. Streams (frames, arm state) use a
//! small queue that drops the oldest entry under load and Zenoh's `CongestionControl::Drop` at
//! priority `DataLow`;
//! results (clouds, views, fruits, maps, status) use a bounded queue the producer waits on and
//! `CongestionControl::Block`. Subscribers decode every payload through the verified codec of
//! `glasshouse-proto`; a payload that fails is counted in [`DropCounters`] and skipped.

mod config;
pub mod metrics;
pub mod probe;
mod queue;
pub mod recovery;

pub use config::{router_config, zenoh_config};

use std::marker::PhantomData;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use glasshouse_proto::keys::{self, Key};
use glasshouse_proto::{
    decode, decode_as, decode_typed, encode, Header, Message, MessageKind, Wire,
};
use queue::{Overflow, SampleQueue};
use zenoh::qos::{CongestionControl, Priority};
use zenoh::Session;

pub use zenoh;

#[derive(thiserror::Error, Debug)]
pub enum BusError {
    #[error("zenoh configuration: {0}")]
    Config(String),
    #[error("settings file {0}")]
    Settings(String),
    #[error("cannot open the zenoh session: {0}")]
    Open(String),
    #[error("cannot declare {what} on {key}: {reason}")]
    Declare {
        what: &'static str,
        key: String,
        reason: String,
    },
    #[error("the publisher task for {0} has stopped")]
    Closed(String),
    #[error(transparent)]
    Key(#[from] keys::KeyError),
}

pub type Result<T, E = BusError> = std::result::Result<T, E>;

/// The Zenoh role of a process.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    Peer,
    Client,
    Router,
}

impl Mode {
    fn as_str(self) -> &'static str {
        match self {
            Mode::Peer => "peer",
            Mode::Client => "client",
            Mode::Router => "router",
        }
    }
}

/// Session flags shared by every Glasshouse binary.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct BusArgs {
    /// Zenoh configuration file (JSON5, Zenoh's own format), merged over the project's defaults
    /// (multicast off, clients retry forever); the flags below override it.
    #[arg(
        long = "zenoh-config",
        value_name = "FILE",
        env = "GLASSHOUSE_ZENOH_CONFIG"
    )]
    pub zenoh_config: Option<PathBuf>,
    /// Endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable).
    #[arg(short = 'e', long = "connect", value_name = "ENDPOINT")]
    pub connect: Vec<String>,
    /// Endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable).
    #[arg(short = 'l', long = "listen", value_name = "ENDPOINT")]
    pub listen: Vec<String>,
    /// Zenoh mode [default: peer, or the config file's].
    #[arg(long, value_enum)]
    pub mode: Option<Mode>,
    /// Link lease in milliseconds: a peer that goes silent this long is dropped and its
    /// liveliness tokens with it (how fast a planner cluster notices a lost member) [default:
    /// Zenoh's 10000, or the config file's].
    #[arg(long = "lease-ms", value_name = "MS", value_parser = clap::value_parser!(u64).range(100..=3_600_000))]
    pub lease_ms: Option<u64>,
}

impl BusArgs {
    /// Client session connecting to `endpoint`.
    pub fn client(endpoint: &str) -> Self {
        Self {
            connect: vec![endpoint.to_owned()],
            mode: Some(Mode::Client),
            ..Self::default()
        }
    }

    /// Router session listening on `endpoint`.
    pub fn router(endpoint: &str) -> Self {
        Self {
            listen: vec![endpoint.to_owned()],
            mode: Some(Mode::Router),
            ..Self::default()
        }
    }
}

/// How each process of a fleet run inside one process (the demo, the tests) opens its session.
#[derive(Clone, Debug)]
pub struct FleetSessions {
    /// Where clients connect.
    pub endpoint: String,
    pub router: BusArgs,
    pub dashboard: BusArgs,
    pub detector: BusArgs,
    pub planner: BusArgs,
    pub edge: BusArgs,
}

impl FleetSessions {
    /// Plain clients of a router listening on `endpoint`.
    pub fn plain(endpoint: &str) -> Self {
        let client = BusArgs::client(endpoint);
        Self {
            endpoint: endpoint.to_owned(),
            router: BusArgs::router(endpoint),
            dashboard: client.clone(),
            detector: client.clone(),
            planner: client.clone(),
            edge: client,
        }
    }
}

/// Opens a session with the shared flags.
pub async fn open(args: &BusArgs) -> Result<Session> {
    let config = zenoh_config(args)?;
    zenoh::open(config)
        .await
        .map_err(|e| BusError::Open(e.to_string()))
}

/// How a key's data travels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Delivery {
    /// Sensor streams: a slow consumer loses old samples, never memory.
    Stream,
    /// Results and control: never dropped by the bus; producers wait for queue space.
    Reliable,
    /// A read-only observer (the dashboard): a deep queue that drops the oldest rather than
    /// ever pushing back on the fleet.
    Monitor,
    /// Reliable, and a subscriber that missed a sample gets it again from the publisher's
    /// cache, in order ([`recovery`]).
    Recovered,
}

/// Counts of messages a process dropped, by cause.
#[derive(Debug, Default)]
pub struct DropCounters {
    /// Payloads that failed verification or decoding.
    pub corrupt: AtomicU64,
    /// Stream samples dropped because a queue was full.
    pub overflow: AtomicU64,
    /// Messages dropped because they came under an older ownership epoch than the newest the
    /// service had seen for their trolley (a replaced owner's views, map updates, fruits or
    /// snapshots); counted by the service's state machine, mirrored here by its driver.
    pub stale_epoch: AtomicU64,
    /// Samples of a [`Delivery::Recovered`] key that a subscriber saw it missed (a gap in the
    /// publisher's numbers) and could not get again from the publisher's cache.
    pub unrecovered: AtomicU64,
}

impl DropCounters {
    pub fn total(&self) -> u64 {
        self.corrupt.load(Ordering::Relaxed)
            + self.overflow.load(Ordering::Relaxed)
            + self.stale_epoch.load(Ordering::Relaxed)
            + self.unrecovered.load(Ordering::Relaxed)
    }
}

impl From<keys::Qos> for Delivery {
    fn from(qos: keys::Qos) -> Self {
        match qos {
            keys::Qos::Stream => Delivery::Stream,
            keys::Qos::Reliable => Delivery::Reliable,
            keys::Qos::Recovered => Delivery::Recovered,
        }
    }
}

/// A publisher of raw payloads on one key expression, whose network writes happen on its own
/// task. [`Publisher`] wraps it; used directly only to inject faults.
pub struct RawPublisher {
    key: String,
    queue: Arc<SampleQueue<Vec<u8>>>,
    task: tokio::task::JoinHandle<()>,
}

impl RawPublisher {
    /// Declares a publisher on `key` and starts its task.
    pub async fn declare(
        session: &Session,
        key: &str,
        delivery: Delivery,
        counters: Arc<DropCounters>,
    ) -> Result<Self> {
        let (congestion, priority, capacity, overflow) = match delivery {
            // Streams go below results: a link that cannot keep up drops frames, while views,
            // fruits and map updates, queued at a higher priority, are never stuck behind them.
            Delivery::Stream => (
                CongestionControl::Drop,
                Priority::DataLow,
                2,
                Overflow::DropOldest,
            ),
            Delivery::Reliable | Delivery::Monitor | Delivery::Recovered => {
                (CongestionControl::Block, Priority::Data, 64, Overflow::Wait)
            }
        };
        let recovered = delivery == Delivery::Recovered;
        let publisher =
            recovery::ZenohPublisher::declare(session, key, (congestion, priority), recovered)
                .await
                .map_err(|e| BusError::Declare {
                    what: "publisher",
                    key: key.to_owned(),
                    reason: e.to_string(),
                })?;
        let queue = Arc::new(SampleQueue::new(capacity, overflow, counters));
        let task_queue = queue.clone();
        let task_key = key.to_owned();
        let task = tokio::spawn(async move {
            while let Some(bytes) = task_queue.pop().await {
                if let Err(e) = publisher.put(bytes).await {
                    tracing::warn!(key = %task_key, error = %e, "put failed");
                }
            }
        });
        Ok(Self {
            key: key.to_owned(),
            queue,
            task,
        })
    }

    pub fn key(&self) -> &str {
        &self.key
    }

    /// Queues an encoded payload. Streams never wait; reliable publishers wait for space.
    pub async fn publish_bytes(&self, bytes: Vec<u8>) -> Result<()> {
        if self.queue.push(bytes).await {
            Ok(())
        } else {
            Err(BusError::Closed(self.key.clone()))
        }
    }

    /// Sends what is queued, then stops the task.
    pub async fn close(self) {
        self.queue.close();
        let _ = tokio::time::timeout(Duration::from_secs(2), self.task).await;
    }
}

/// A publisher of `M` on one key.
pub struct Publisher<M> {
    raw: RawPublisher,
    _message: PhantomData<fn(M)>,
}

impl<M: Wire> Publisher<M> {
    /// Declares a publisher on `key` with the key's delivery ([`Key::qos`]).
    pub async fn declare(
        session: &Session,
        key: &Key<M>,
        counters: Arc<DropCounters>,
    ) -> Result<Self> {
        let delivery = key.qos().into();
        let raw = RawPublisher::declare(session, key.as_str(), delivery, counters).await?;
        Ok(Self {
            raw,
            _message: PhantomData,
        })
    }

    pub fn key(&self) -> &str {
        self.raw.key()
    }

    /// Encodes and queues one message. Streams never wait; reliable publishers wait for space.
    pub async fn publish(&self, header: &Header, message: &M) -> Result<()> {
        self.raw.publish_bytes(encode(header, message)).await
    }

    /// Queues an already encoded payload (also used to inject faults in tests).
    pub async fn publish_bytes(&self, bytes: Vec<u8>) -> Result<()> {
        self.raw.publish_bytes(bytes).await
    }

    /// Sends what is queued, then stops the task.
    pub async fn close(self) {
        self.raw.close().await;
    }
}

/// One received, verified and decoded message: `M` for a typed [`Subscriber`], [`Message`] for
/// an [`AnySubscriber`].
#[derive(Clone, Debug)]
pub struct Received<M> {
    pub key: String,
    pub header: Header,
    pub message: M,
    /// The verified envelope as it arrived (for recorders that keep the bytes).
    pub payload: Vec<u8>,
    /// When the subscriber's callback took it off the wire: how long it then waited in the
    /// queue tells a busy receiver from a slow sender.
    pub arrived_at: std::time::Instant,
}

/// The queue between a Zenoh subscriber callback and the decoding `recv` of both subscribers.
struct Inbox {
    queue: Arc<SampleQueue<(String, Vec<u8>, std::time::Instant)>>,
    counters: Arc<DropCounters>,
    _subscriber: recovery::ZenohSubscriber,
}

impl Inbox {
    async fn declare(
        session: &Session,
        key_expr: &str,
        delivery: Delivery,
        counters: Arc<DropCounters>,
    ) -> Result<Self> {
        let (capacity, overflow) = match delivery {
            Delivery::Stream => (2, Overflow::DropOldest),
            Delivery::Reliable | Delivery::Recovered => (256, Overflow::Wait),
            Delivery::Monitor => (1024, Overflow::DropOldest),
        };
        let queue = Arc::new(SampleQueue::new(capacity, overflow, counters.clone()));
        let cb_queue = queue.clone();
        let callback = move |sample: zenoh::sample::Sample| {
            let key = sample.key_expr().as_str().to_owned();
            let bytes = sample.payload().to_bytes().into_owned();
            cb_queue.push_blocking((key, bytes, std::time::Instant::now()));
        };
        let recovered = delivery == Delivery::Recovered;
        let subscriber = recovery::ZenohSubscriber::declare(
            session,
            key_expr,
            recovered,
            counters.clone(),
            callback,
        )
        .await
        .map_err(|e| BusError::Declare {
            what: "subscriber",
            key: key_expr.to_owned(),
            reason: e.to_string(),
        })?;
        Ok(Self {
            queue,
            counters,
            _subscriber: subscriber,
        })
    }

    /// The next payload that `decode` accepts; the others are counted and skipped.
    async fn recv<T>(
        &self,
        decode: impl Fn(&str, &[u8]) -> DecodeResult<T>,
    ) -> Option<Received<T>> {
        loop {
            let (key, bytes, arrived_at) = self.queue.pop().await?;
            if let Some(received) = self.accept(key, bytes, arrived_at, &decode) {
                return Some(received);
            }
        }
    }

    /// Like [`Inbox::recv`], but only from what has already arrived.
    fn try_recv<T>(&self, decode: impl Fn(&str, &[u8]) -> DecodeResult<T>) -> Option<Received<T>> {
        loop {
            let (key, bytes, arrived_at) = self.queue.try_pop()?;
            if let Some(received) = self.accept(key, bytes, arrived_at, &decode) {
                return Some(received);
            }
        }
    }

    /// Decodes one payload, or counts and logs it as corrupt.
    fn accept<T>(
        &self,
        key: String,
        bytes: Vec<u8>,
        arrived_at: std::time::Instant,
        decode: &impl Fn(&str, &[u8]) -> DecodeResult<T>,
    ) -> Option<Received<T>> {
        match decode(&key, &bytes) {
            Ok((header, message)) => Some(Received {
                key,
                header,
                message,
                payload: bytes,
                arrived_at,
            }),
            Err(e) => {
                let n = self.counters.corrupt.fetch_add(1, Ordering::Relaxed) + 1;
                // Log the first few and then every hundredth: a flood must not flood the log.
                if n <= 5 || n.is_multiple_of(100) {
                    tracing::warn!(%key, bytes = bytes.len(), error = %e, dropped = n, "dropped a bad payload");
                }
                None
            }
        }
    }
}

type DecodeResult<T> = glasshouse_proto::Result<(Header, T)>;

/// A subscriber of `M` on a key (or a wildcard of such keys): every payload must decode as `M`,
/// the others are counted in [`DropCounters::corrupt`] and skipped.
pub struct Subscriber<M> {
    inbox: Inbox,
    _message: PhantomData<fn() -> M>,
}

impl<M: Wire> Subscriber<M> {
    /// Subscribes to `key` with the key's default delivery.
    pub async fn declare(
        session: &Session,
        key: &Key<M>,
        counters: Arc<DropCounters>,
    ) -> Result<Self> {
        Self::declare_with(session, key, key.qos().into(), counters).await
    }

    /// Subscribes to `key` with an explicit delivery (e.g. [`Delivery::Monitor`]).
    pub async fn declare_with(
        session: &Session,
        key: &Key<M>,
        delivery: Delivery,
        counters: Arc<DropCounters>,
    ) -> Result<Self> {
        let inbox = Inbox::declare(session, key.as_str(), delivery, counters).await?;
        Ok(Self {
            inbox,
            _message: PhantomData,
        })
    }

    /// The next message that decodes; `None` once the subscriber is closed.
    pub async fn recv(&self) -> Option<Received<M>> {
        self.inbox.recv(|_, bytes| decode_typed::<M>(bytes)).await
    }

    /// The next message that decodes among those already received, without waiting.
    pub fn try_recv(&self) -> Option<Received<M>> {
        self.inbox.try_recv(|_, bytes| decode_typed::<M>(bytes))
    }
}

/// A subscriber of every kind on a key expression (the dashboard's `gh/**`, recorders).
pub struct AnySubscriber {
    inbox: Inbox,
}

impl AnySubscriber {
    /// Subscribes to `key_expr`. The expected message kind comes from each key (see
    /// [`keys::parse`]); payloads on keys outside the tree must decode as any kind.
    pub async fn declare(
        session: &Session,
        key_expr: &str,
        delivery: Delivery,
        counters: Arc<DropCounters>,
    ) -> Result<Self> {
        let inbox = Inbox::declare(session, key_expr, delivery, counters).await?;
        Ok(Self { inbox })
    }

    /// The next message that decodes; `None` once the subscriber is closed.
    pub async fn recv(&self) -> Option<Received<Message>> {
        self.inbox
            .recv(|key, bytes| match Self::expected_kind(key) {
                Some(kind) => decode_as(bytes, kind),
                None => decode(bytes),
            })
            .await
    }

    /// The kind expected on a key of this project's tree.
    pub fn expected_kind(key: &str) -> Option<MessageKind> {
        keys::parse(key).and_then(|k| k.message_kind())
    }
}

/// Declares this process's liveliness token; keep it alive for as long as the process is a member.
pub async fn declare_alive(
    session: &Session,
    kind: keys::MemberKind,
    id: &str,
) -> Result<zenoh::liveliness::LivelinessToken> {
    let key = keys::alive(kind, id)?;
    session
        .liveliness()
        .declare_token(key.clone())
        .await
        .map_err(|e| BusError::Declare {
            what: "liveliness token",
            key,
            reason: e.to_string(),
        })
}

/// A member joining or leaving, from its liveliness token.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum MemberEvent {
    Joined(String),
    /// Token undeclared, session closed, or link lease expired.
    Left(String),
}

/// How long after a leave [`MemberWatch`] asks the routers whether the member's token is still
/// declared. With two routers a leave can be stale: a member that moved to the other router has
/// declared its token there before the first router's undeclaration of it arrives. Asked at
/// once, the question can be answered from the watcher's own copy of the token before the leave
/// is applied; a second later the leave has been applied everywhere it will be.
pub const LEAVE_RECHECK_AFTER: Duration = Duration::from_secs(1);

/// How many events each member has had, so that a recheck re-joins a member only when the leave
/// it was for is still the latest news of it.
#[derive(Debug, Default)]
struct MemberNews {
    events: std::collections::HashMap<String, u64>,
}

impl MemberNews {
    /// Notes an event of `id`; its number.
    fn heard(&mut self, id: &str) -> u64 {
        let count = self.events.entry(id.to_owned()).or_default();
        *count += 1;
        *count
    }

    /// Whether `id`, found alive after its event number `after`, joins again: only when nothing
    /// was heard of it since (that re-join is then its latest news).
    fn rejoins(&mut self, id: &str, after: u64) -> bool {
        let latest = self.events.get(id).copied().unwrap_or(0) == after;
        if latest {
            self.heard(id);
        }
        latest
    }
}

/// Follows the liveliness tokens of one kind of member: the ones alive when it starts come first
/// as [`MemberEvent::Joined`], then every change. Every leave is passed on at once and checked
/// again [`LEAVE_RECHECK_AFTER`] later: a member whose token the routers still hold then, with
/// no other news of it since, joins again (the leave was stale).
pub struct MemberWatch {
    subscriber:
        zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    session: Session,
    kind: keys::MemberKind,
    news: MemberNews,
    rechecks: tokio::sync::mpsc::UnboundedSender<(String, u64)>,
    still_alive: tokio::sync::mpsc::UnboundedReceiver<(String, u64)>,
}

impl MemberWatch {
    pub async fn declare(session: &Session, kind: keys::MemberKind) -> Result<Self> {
        let key = keys::alive_all(kind);
        let subscriber = session
            .liveliness()
            .declare_subscriber(key.clone())
            .history(true)
            .await
            .map_err(|e| BusError::Declare {
                what: "liveliness subscriber",
                key,
                reason: e.to_string(),
            })?;
        let (rechecks, still_alive) = tokio::sync::mpsc::unbounded_channel();
        Ok(Self {
            subscriber,
            session: session.clone(),
            kind,
            news: MemberNews::default(),
            rechecks,
            still_alive,
        })
    }

    /// The next join or leave; `None` once the session is closed.
    pub async fn recv(&mut self) -> Option<MemberEvent> {
        loop {
            let event = tokio::select! {
                sample = self.subscriber.recv_async() => self.on_sample(&sample.ok()?),
                Some((id, after)) = self.still_alive.recv() => self.on_still_alive(id, after),
            };
            if event.is_some() {
                return event;
            }
        }
    }

    fn on_sample(&mut self, sample: &zenoh::sample::Sample) -> Option<MemberEvent> {
        let keys::ParsedKey::Alive { id, .. } = keys::parse(sample.key_expr().as_str())? else {
            return None;
        };
        let count = self.news.heard(&id);
        Some(match sample.kind() {
            zenoh::sample::SampleKind::Put => MemberEvent::Joined(id),
            zenoh::sample::SampleKind::Delete => {
                self.recheck(id.clone(), count);
                MemberEvent::Left(id)
            }
        })
    }

    /// A member found alive after its leave number `after`: it joins again unless other news of
    /// it came since.
    fn on_still_alive(&mut self, id: String, after: u64) -> Option<MemberEvent> {
        if !self.news.rejoins(&id, after) {
            return None;
        }
        tracing::warn!(member = %id, kind = self.kind.as_str(),
            "a member's leave was stale (its token is still declared): it joins again");
        Some(MemberEvent::Joined(id))
    }

    /// Asks the routers for the live members [`LEAVE_RECHECK_AFTER`] after `id`'s leave (the
    /// query [`live_members`] makes, which the ACL grants a watcher).
    fn recheck(&self, id: String, after: u64) {
        let (session, kind, found) = (self.session.clone(), self.kind, self.rechecks.clone());
        tokio::spawn(async move {
            tokio::time::sleep(LEAVE_RECHECK_AFTER).await;
            if live_members(&session, kind).await.contains(&id) {
                let _ = found.send((id, after));
            }
        });
    }
}

/// Answers queries for `M` on a key expression (a planner's map snapshots).
pub struct Responder<M> {
    queryable: zenoh::query::Queryable<zenoh::handlers::FifoChannelHandler<zenoh::query::Query>>,
    _message: PhantomData<fn(M)>,
}

impl<M: Wire> Responder<M> {
    pub async fn declare(session: &Session, key: &Key<M>) -> Result<Self> {
        let queryable = session
            .declare_queryable(key.as_str().to_owned())
            .await
            .map_err(|e| BusError::Declare {
                what: "queryable",
                key: key.as_str().to_owned(),
                reason: e.to_string(),
            })?;
        Ok(Self {
            queryable,
            _message: PhantomData,
        })
    }

    /// The next query; `None` once the session is closed.
    pub async fn recv(&self) -> Option<zenoh::query::Query> {
        self.queryable.recv_async().await.ok()
    }

    /// Replies to `query` with one message, or with an error text the asker can log.
    /// Answers `query` with a message (or declines it); the bytes of the message sent, 0 for a
    /// refusal or a failed reply.
    pub async fn reply(
        &self,
        query: &zenoh::query::Query,
        answer: Result<(Header, M), String>,
    ) -> usize {
        let key = query.key_expr().clone();
        let (outcome, bytes) = match answer {
            Ok((header, message)) => {
                let payload = encode(&header, &message);
                let bytes = payload.len();
                (query.reply(key, payload).await, bytes)
            }
            Err(reason) => (query.reply_err(reason).await, 0),
        };
        match outcome {
            Ok(()) => bytes,
            Err(e) => {
                tracing::warn!(key = %query.key_expr(), error = %e, "reply failed");
                0
            }
        }
    }
}

/// Why [`ask`] got no message.
#[derive(thiserror::Error, Debug)]
pub enum AskError {
    #[error("no reply within {0:?}")]
    NoReply(Duration),
    #[error("the responder declined: {0}")]
    Declined(String),
    #[error("the reply did not decode: {0}")]
    Corrupt(String),
    #[error("query failed: {0}")]
    Query(String),
}

/// Queries `key` (a concrete key of the tree) and returns the first reply, verified as `M`.
pub async fn ask<M: Wire>(
    session: &Session,
    key: &Key<M>,
    timeout: Duration,
) -> Result<(Header, M), AskError> {
    ask_with(session, key, "", timeout).await
}

/// [`ask`] with selector parameters (`name=value;…`, as Zenoh's selectors write them; empty for
/// none), which the queryable reads with `Query::parameters`.
pub async fn ask_with<M: Wire>(
    session: &Session,
    key: &Key<M>,
    parameters: &str,
    timeout: Duration,
) -> Result<(Header, M), AskError> {
    let selector = match parameters {
        "" => key.as_str().to_owned(),
        p => format!("{}?{p}", key.as_str()),
    };
    let replies = session
        .get(selector)
        .timeout(timeout)
        .await
        .map_err(|e| AskError::Query(e.to_string()))?;
    let reply = replies
        .recv_async()
        .await
        .map_err(|_| AskError::NoReply(timeout))?;
    match reply.result() {
        Ok(sample) => decode_typed::<M>(&sample.payload().to_bytes())
            .map_err(|e| AskError::Corrupt(e.to_string())),
        Err(err) => Err(AskError::Declined(
            String::from_utf8_lossy(&err.payload().to_bytes()).into_owned(),
        )),
    }
}

/// The ids of the live members of a kind right now.
pub async fn live_members(session: &Session, kind: keys::MemberKind) -> Vec<String> {
    let mut ids = Vec::new();
    let Ok(replies) = session
        .liveliness()
        .get(keys::alive_all(kind))
        .timeout(Duration::from_secs(1))
        .await
    else {
        return ids;
    };
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            if let Some(keys::ParsedKey::Alive { id, .. }) = keys::parse(sample.key_expr().as_str())
            {
                ids.push(id);
            }
        }
    }
    ids.sort();
    ids.dedup();
    ids
}

/// This machine's wall clock in ns since the Unix epoch (0 if it reads before 1970). A service
/// reads it once at start for its boot epoch ([`glasshouse_proto::Header::epoch_ns`]) and passes
/// it, and the time of each event, into its state machine.
pub fn wall_clock_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}

/// Resolves on Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}

/// Zenoh runtime pools for a process that opens many sessions (`ZENOH_RUNTIME` syntax).
///
/// All sessions of a process share Zenoh's runtime pools. When one process holds a router and
/// the sessions it routes to (the demo, the benches), the default pools are small enough that a
/// router blocked on a full reliable queue can hold every receive thread, so nothing drains the
/// link it waits on: measured, 8 trolleys at 5 frames/s of 640x480 stalled within 35 s, and kept
/// up with these pools.
pub const IN_PROCESS_ZENOH_RUNTIME: &str = "(rx: (worker_threads: 8), net: (worker_threads: 8))";

/// Gives a process that runs many sessions larger Zenoh pools ([`IN_PROCESS_ZENOH_RUNTIME`]),
/// unless the user set `ZENOH_RUNTIME`. Call it first in `main`, before any session opens.
pub fn use_in_process_runtime_pools() {
    if std::env::var_os("ZENOH_RUNTIME").is_none() {
        std::env::set_var("ZENOH_RUNTIME", IN_PROCESS_ZENOH_RUNTIME);
    }
}

/// Logs to stderr, filtered by `RUST_LOG` (default: info for Glasshouse, warn for the rest).
pub fn init_tracing() {
    let filter = tracing_subscriber_filter();
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

fn tracing_subscriber_filter() -> tracing_subscriber::EnvFilter {
    tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn,glasshouse=info,edge=info,planner_service=info,detector_service=info,dashboard=info,glasshouse_edge=info,glasshouse_planner=info,glasshouse_detector=info,glasshouse_dashboard=info"))
}

/// A cloneable stop signal for service loops.
#[derive(Clone, Debug)]
pub struct Shutdown(tokio::sync::watch::Receiver<bool>);

/// Fires a [`Shutdown`].
#[derive(Debug)]
pub struct ShutdownTrigger(tokio::sync::watch::Sender<bool>);

impl Shutdown {
    pub fn new() -> (ShutdownTrigger, Shutdown) {
        let (tx, rx) = tokio::sync::watch::channel(false);
        (ShutdownTrigger(tx), Shutdown(rx))
    }

    pub fn is_set(&self) -> bool {
        *self.0.borrow()
    }

    /// Resolves once the trigger fired (or was dropped).
    pub async fn wait(&mut self) {
        let _ = self.0.wait_for(|&stop| stop).await;
    }
}

impl ShutdownTrigger {
    pub fn fire(&self) {
        let _ = self.0.send(true);
    }

    /// Fires on Ctrl-C or SIGTERM.
    pub fn fire_on_signal(self) {
        tokio::spawn(async move {
            shutdown_signal().await;
            tracing::info!("shutting down");
            self.fire();
        });
    }
}

/// Reads a service's JSON5 settings file, or the defaults when no file is given.
pub fn load_settings<T: serde::de::DeserializeOwned + Default>(
    path: Option<&std::path::Path>,
) -> Result<T> {
    let Some(path) = path else {
        return Ok(T::default());
    };
    let text = std::fs::read_to_string(path)
        .map_err(|e| BusError::Settings(format!("{}: {e}", path.display())))?;
    json5::from_str(&text).map_err(|e| BusError::Settings(format!("{}: {e}", path.display())))
}

/// The flags every service binary shares: its settings file and its session.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct ServiceArgs {
    /// Settings file (JSON5); the flags given here override it.
    #[arg(short, long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    #[command(flatten)]
    pub bus: BusArgs,
    /// Serve OpenMetrics on http://ADDR/metrics (e.g. 127.0.0.1:9464) for Prometheus: counts,
    /// drops by reason, gauges and, in the planner, stage times as histograms.
    #[arg(long, value_name = "ADDR")]
    pub metrics: Option<String>,
}

/// The whole `main` of a service binary: logs to stderr, parses the binary's own flags `C`
/// plus [`ServiceArgs`], builds the settings `S` (defaults, then `--config`, then `flags`,
/// which applies the binary's flags and validates), and runs `service` on a multi-threaded
/// runtime, with fresh counters `K`, until Ctrl-C or SIGTERM.
pub fn service_main<C, S, K, E, Fut>(
    flags: impl FnOnce(C, &mut S) -> Result<(), E>,
    service: impl FnOnce(Session, S, Shutdown, Arc<K>) -> Fut,
) -> Result<(), E>
where
    C: clap::Parser,
    S: serde::de::DeserializeOwned + Default,
    K: Default + metrics::ServiceMetrics,
    E: From<BusError> + From<std::io::Error>,
    Fut: std::future::Future<Output = Result<(), E>>,
{
    use clap::{Args, FromArgMatches};
    init_tracing();
    let command = C::command();
    // The flattened flags' doc comments would otherwise replace the binary's own description.
    let (about, long_about) = (
        command.get_about().cloned(),
        command.get_long_about().cloned(),
    );
    let mut command = ServiceArgs::augment_args(command);
    if let Some(about) = about {
        command = command.about(about);
    }
    if let Some(long_about) = long_about {
        command = command.long_about(long_about);
    }
    let matches = command.get_matches();
    let parsed = C::from_arg_matches(&matches).and_then(|cli| {
        ServiceArgs::from_arg_matches(&matches).map(|service_args| (cli, service_args))
    });
    let (cli, service_args) = parsed.unwrap_or_else(|e| e.exit());
    let mut settings = load_settings(service_args.config.as_deref())?;
    flags(cli, &mut settings)?;
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?
        .block_on(run_service(
            &service_args.bus,
            |session, shutdown| async move {
                let counters: Arc<K> = Arc::default();
                if let Some(addr) = &service_args.metrics {
                    let registry = metrics::registry_of(counters.clone());
                    metrics::serve(addr, registry, shutdown.clone()).await?;
                }
                service(session, settings, shutdown, counters).await
            },
        ))
}

/// Overrides a setting with a flag, when the flag was given.
pub fn set_flag<T>(setting: &mut T, flag: Option<T>) {
    if let Some(value) = flag {
        *setting = value;
    }
}

/// Runs a service binary's loop on its own session: opens the session from `args`, hands it
/// and a [`Shutdown`] that fires on Ctrl-C or SIGTERM to `service`, and closes the session once
/// the service returns.
pub async fn run_service<F, Fut, E>(args: &BusArgs, service: F) -> Result<(), E>
where
    F: FnOnce(Session, Shutdown) -> Fut,
    Fut: std::future::Future<Output = Result<(), E>>,
    E: From<BusError>,
{
    let session = open(args).await?;
    let (trigger, shutdown) = Shutdown::new();
    trigger.fire_on_signal();
    let result = service(session.clone(), shutdown).await;
    let _ = session.close().await;
    result
}

#[cfg(test)]
mod member_news_tests {
    use super::MemberNews;

    #[test]
    fn a_recheck_rejoins_only_the_latest_leave() {
        let mut news = MemberNews::default();
        assert_eq!(news.heard("t1"), 1); // joined
        let leave = news.heard("t1");
        // Found alive after the leave, nothing heard since: joins again, once.
        assert!(news.rejoins("t1", leave));
        assert!(!news.rejoins("t1", leave));
        // A leave followed by a join: the recheck of the leave is old news.
        let leave = news.heard("t1");
        news.heard("t1");
        assert!(!news.rejoins("t1", leave));
        // Two leaves in a row: only the second's recheck counts.
        let first = news.heard("t2");
        let second = news.heard("t2");
        assert!(!news.rejoins("t2", first));
        assert!(news.rejoins("t2", second));
        // A member never heard of is not made up.
        assert!(!news.rejoins("t3", 1));
    }
}
