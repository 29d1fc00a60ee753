//! Foxglove live: a Foxglove WebSocket server beside Rerun, so Foxglove opens a running fleet as
//! it opens a recording. The server is the `foxglove` crate's (Foxglove's own SDK: the protocol,
//! client subscriptions and per-client queues are theirs). The channels are the MCAP
//! recorder's: every key with our flatbuffer message and its binary schema, and the same
//! content in Foxglove's well-known schemas as JSON.
//!
//! Conversion runs on its own thread behind a bounded queue (a full queue is a counted drop),
//! and only for channels a client subscribes to: with nobody watching, the server costs the
//! dashboard a channel lookup per message. Each channel's latest message that found no
//! subscriber is kept and sent once one subscribes (a channel is advertised with its first
//! message, so a client subscribes only after that one went by: without this a trolley's fruits,
//! sent once per plan, could be missed until the next). Kept per channel: a client subscribes to
//! each channel when it reads its advertisement, so a key's flatbuffer channel may be watched
//! while the JSON channels made from the same message are not yet.

use std::collections::{HashMap, HashSet};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use anyhow::Context as _;
use foxglove_sdk::{Context, PartialMetadata, RawChannel, Schema, WebSocketServer};
use glasshouse_proto::{SCHEMA_BFBS, SCHEMA_ROOT_NAME};
use serde::Deserialize;

use crate::foxglove::json_schema;
use crate::mcap_recorder::foxglove_messages;

/// Where the server listens, and how much it buffers.
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FoxgloveLiveSettings {
    /// `IP:PORT` (port 0: any free one). Loopback by default: the protocol has no
    /// authentication, so reach it from elsewhere through an SSH tunnel.
    pub listen: String,
    /// Messages waiting for conversion before new ones are dropped.
    pub queue: usize,
}

impl Default for FoxgloveLiveSettings {
    fn default() -> Self {
        Self {
            // Foxglove's default connection string.
            listen: "127.0.0.1:8765".into(),
            queue: 256,
        }
    }
}

/// What the server sent.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct FoxgloveLiveSummary {
    /// Channels advertised.
    pub channels: u64,
    /// Messages sent to at least one subscribed client.
    pub sent: u64,
    /// Messages the converter could not take in time.
    pub dropped: u64,
}

#[derive(Clone)]
struct Entry {
    key: String,
    payload: Vec<u8>,
    log_time_ns: u64,
}

/// The running server.
pub struct FoxgloveLive {
    tx: Option<SyncSender<Entry>>,
    thread: Option<JoinHandle<FoxgloveLiveSummary>>,
    server: Option<foxglove_sdk::WebSocketServerHandle>,
    dropped: AtomicU64,
    /// Keys whose channels exist: until then every message goes to the converter.
    advertised: HashSet<String>,
    port: u16,
}

impl FoxgloveLive {
    /// Starts the server on the current Tokio runtime and the converter thread.
    pub async fn start(settings: &FoxgloveLiveSettings) -> anyhow::Result<Self> {
        let addr: SocketAddr = settings
            .listen
            .parse()
            .with_context(|| format!("foxglove listen {:?}: not IP:PORT", settings.listen))?;
        let context = Context::new();
        let server = WebSocketServer::new()
            .name("glasshouse")
            .context(&context)
            .bind(addr.ip().to_string(), addr.port())
            .start()
            .await
            .with_context(|| format!("cannot serve Foxglove on {addr}"))?;
        let port = server.port();
        let (tx, rx) = sync_channel(settings.queue.max(1));
        let thread = std::thread::Builder::new()
            .name("foxglove-live".into())
            .spawn(move || Channels::new(context).run(rx))?;
        tracing::info!(%addr, port, "Foxglove live: open ws://{}:{port} in Foxglove", addr.ip());
        Ok(Self {
            tx: Some(tx),
            thread: Some(thread),
            server: Some(server),
            dropped: AtomicU64::new(0),
            advertised: HashSet::new(),
            port,
        })
    }

    /// The port the server listens on.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// Offers the verified envelope `payload` that arrived on `key`: it is converted and sent
    /// when a client is connected (and once per key, so its channels are advertised).
    pub fn offer(&mut self, key: &str, payload: &[u8], log_time_ns: u64) {
        let watched = self.server.as_ref().is_some_and(|s| s.client_count() > 0);
        let first = !self.advertised.contains(key);
        if !(watched || first) {
            return;
        }
        let Some(tx) = &self.tx else { return };
        let entry = Entry {
            key: key.to_string(),
            payload: payload.to_vec(),
            log_time_ns,
        };
        match tx.try_send(entry) {
            Ok(()) => {
                if first {
                    self.advertised.insert(key.to_string());
                }
            }
            Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => {
                let n = self.dropped.fetch_add(1, Ordering::Relaxed) + 1;
                if n <= 5 || n.is_multiple_of(100) {
                    tracing::warn!(dropped = n, "Foxglove live cannot keep up: message dropped");
                }
            }
        }
    }

    /// Stops the server (clients are disconnected) and says what was sent.
    pub async fn finish(mut self) -> FoxgloveLiveSummary {
        drop(self.tx.take());
        let mut summary = match self.thread.take().map(|t| t.join()) {
            Some(Ok(summary)) => summary,
            _ => FoxgloveLiveSummary::default(),
        };
        if let Some(server) = self.server.take() {
            server.stop().wait().await;
        }
        summary.dropped = self.dropped.load(Ordering::Relaxed);
        summary
    }
}

/// How often the converter looks for new subscribers of kept messages when no message arrives.
const PENDING_POLL: Duration = Duration::from_millis(100);

/// A channel's latest message that reached no subscriber.
struct Pending {
    channel: Arc<RawChannel>,
    bytes: Vec<u8>,
    log_time_ns: u64,
}

/// The converter: channels by topic, created as keys first appear.
struct Channels {
    context: Arc<Context>,
    by_topic: HashMap<String, Arc<RawChannel>>,
    /// The Foxglove topics each key's messages convert to.
    json_topics: HashMap<String, Vec<String>>,
    /// Per channel (by topic), its latest message that reached no subscriber. Kept per channel,
    /// not per key: a client subscribes to each advertised channel on its own, so one key's
    /// flatbuffer channel can be watched while its JSON channels are not yet.
    pending: HashMap<String, Pending>,
    summary: FoxgloveLiveSummary,
}

impl Channels {
    fn new(context: Arc<Context>) -> Self {
        Self {
            context,
            by_topic: HashMap::new(),
            json_topics: HashMap::new(),
            pending: HashMap::new(),
            summary: FoxgloveLiveSummary::default(),
        }
    }

    fn run(mut self, rx: Receiver<Entry>) -> FoxgloveLiveSummary {
        loop {
            match rx.recv_timeout(PENDING_POLL) {
                Ok(entry) => {
                    self.send_pending();
                    self.send(&entry);
                }
                Err(RecvTimeoutError::Timeout) => self.send_pending(),
                Err(RecvTimeoutError::Disconnected) => break,
            }
        }
        self.summary
    }

    fn channel(&mut self, topic: &str, encoding: &str, schema: Schema) -> Option<Arc<RawChannel>> {
        if let Some(channel) = self.by_topic.get(topic) {
            return Some(channel.clone());
        }
        let built = self
            .context
            .channel_builder(topic)
            .message_encoding(encoding)
            .schema(schema)
            .build_raw();
        match built {
            Ok(channel) => {
                self.summary.channels += 1;
                self.by_topic.insert(topic.to_string(), channel.clone());
                Some(channel)
            }
            Err(e) => {
                tracing::warn!(topic, "no Foxglove channel: {e}");
                None
            }
        }
    }

    /// Sends to the channel's subscribers, or keeps the message until one subscribes.
    fn log(&mut self, channel: Arc<RawChannel>, bytes: &[u8], log_time_ns: u64) {
        let topic = channel.topic().to_string();
        if !channel.has_sinks() {
            let pending = Pending {
                channel,
                bytes: bytes.to_vec(),
                log_time_ns,
            };
            self.pending.insert(topic, pending);
            return;
        }
        channel.log_with_meta(bytes, PartialMetadata::with_log_time(log_time_ns));
        self.pending.remove(&topic);
        self.summary.sent += 1;
    }

    /// Sends the kept messages whose channels have a subscriber now.
    fn send_pending(&mut self) {
        let ready: Vec<String> = self
            .pending
            .iter()
            .filter(|(_, p)| p.channel.has_sinks())
            .map(|(topic, _)| topic.clone())
            .collect();
        for topic in ready {
            if let Some(p) = self.pending.remove(&topic) {
                p.channel
                    .log_with_meta(&p.bytes, PartialMetadata::with_log_time(p.log_time_ns));
                self.summary.sent += 1;
            }
        }
    }

    /// Whether `topic` has a subscriber.
    fn subscribed(&self, topic: &str) -> bool {
        self.by_topic.get(topic).is_some_and(|c| c.has_sinks())
    }

    /// Converts and sends `entry` (kept per channel when it reaches no subscriber).
    fn send(&mut self, entry: &Entry) {
        let flat = Schema::new(SCHEMA_ROOT_NAME, "flatbuffer", SCHEMA_BFBS);
        if let Some(channel) = self.channel(&entry.key, "flatbuffer", flat) {
            self.log(channel, &entry.payload, entry.log_time_ns);
        }
        // Converting costs (images become base64 JSON): only for a first advertisement or a
        // subscribed channel (an unwatched one keeps the message it was advertised with).
        let wanted = match self.json_topics.get(&entry.key) {
            None => true,
            Some(topics) => topics.iter().any(|t| self.subscribed(t)),
        };
        if !wanted {
            return;
        }
        let messages = foxglove_messages(&entry.key, &entry.payload);
        if !messages.is_empty() {
            let topics = messages.iter().map(|m| m.topic.clone()).collect();
            self.json_topics.insert(entry.key.clone(), topics);
        }
        for m in messages {
            let schema = Schema::new(m.schema, "jsonschema", json_schema(m.schema));
            if let Some(channel) = self.channel(&m.topic, "json", schema) {
                self.log(channel, &m.json, entry.log_time_ns);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use foxglove_sdk::{ChannelId, FoxgloveError, Metadata, Sink, SinkId};
    use glasshouse_proto::{encode, samples};

    use super::*;

    /// A client that subscribes to the flatbuffer channels when they are advertised and to
    /// the JSON ones only when told: a Foxglove client reads advertisements one at a time.
    struct SlowClient {
        id: SinkId,
        received: Mutex<Vec<String>>,
    }

    impl Sink for SlowClient {
        fn id(&self) -> SinkId {
            self.id
        }

        fn log(&self, channel: &RawChannel, _: &[u8], _: &Metadata) -> Result<(), FoxgloveError> {
            self.received
                .lock()
                .expect("lock")
                .push(channel.topic().to_string());
            Ok(())
        }

        fn add_channels(&self, channels: &[&Arc<RawChannel>]) -> Option<Vec<ChannelId>> {
            let flat = channels
                .iter()
                .filter(|c| c.message_encoding() == "flatbuffer");
            Some(flat.map(|c| c.id()).collect())
        }

        fn auto_subscribe(&self) -> bool {
            false
        }
    }

    /// Detector `d1`'s clouds of trolley `t1`.
    const ROI_KEY: &str = "gh/trolley/t1/roi/d1";

    fn roi_entry(seq: u64) -> Entry {
        Entry {
            key: ROI_KEY.into(),
            payload: encode(&samples::header(seq), &samples::roi_cloud()),
            log_time_ns: seq,
        }
    }

    #[test]
    fn a_json_channel_subscribed_after_its_flatbuffer_channel_still_gets_the_kept_message() {
        let context = Context::new();
        let client = Arc::new(SlowClient {
            id: SinkId::next(),
            received: Mutex::new(Vec::new()),
        });
        context.add_sink(client.clone());
        let mut channels = Channels::new(context.clone());
        channels.send(&roi_entry(1));
        channels.send(&roi_entry(2));
        let received = |topic: &str| {
            let all = client.received.lock().expect("lock");
            all.iter().filter(|t| t.as_str() == topic).count()
        };
        assert_eq!(received(ROI_KEY), 2, "both envelopes");
        assert_eq!(received("/t1/roi"), 0, "nobody watches the point cloud yet");

        let cloud = channels.by_topic["/t1/roi"].id();
        context.subscribe_channels(client.id, &[cloud]);
        channels.send_pending();
        assert_eq!(
            received("/t1/roi"),
            1,
            "the kept point cloud, once subscribed"
        );
        channels.send_pending();
        assert_eq!(received("/t1/roi"), 1, "sent once");
        channels.send(&roi_entry(3));
        assert_eq!(received("/t1/roi"), 2);
        assert_eq!(received(ROI_KEY), 3);
    }
}
