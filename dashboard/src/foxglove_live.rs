//! Foxglove live: a Foxglove WebSocket server beside Rerun, so Foxglove opens a running fleet as
//! it opens a recording. The server is the `foxglove` crate's (Foxglove's own SDK: the protocol,
//! client subscriptions and per-client queues are theirs). The channels are the MCAP
//! recorder's: every key with our flatbuffer message and its binary schema, and the same
//! content in Foxglove's well-known schemas as JSON.
//!
//! Conversion runs on its own thread behind a bounded queue (a full queue is a counted drop),
//! and only for channels a client subscribes to: with nobody watching, the server costs the
//! dashboard a channel lookup per message. A channel's latest message that found no subscriber
//! is kept and sent once one subscribes (a channel is advertised with its first message, so a
//! client subscribes only after that one went by: without this a trolley's fruits, sent once per
//! plan, could be missed until the next).

use std::collections::{HashMap, HashSet};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::Arc;
use std::thread::JoinHandle;

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

/// The converter: channels by topic, created as keys first appear.
struct Channels {
    context: Arc<Context>,
    by_topic: HashMap<String, Arc<RawChannel>>,
    /// The Foxglove topics each key's messages convert to.
    json_topics: HashMap<String, Vec<String>>,
    /// Per key, its latest entry that reached no subscriber.
    unsent: HashMap<String, Entry>,
    summary: FoxgloveLiveSummary,
}

impl Channels {
    fn new(context: Arc<Context>) -> Self {
        Self {
            context,
            by_topic: HashMap::new(),
            json_topics: HashMap::new(),
            unsent: HashMap::new(),
            summary: FoxgloveLiveSummary::default(),
        }
    }

    fn run(mut self, rx: Receiver<Entry>) -> FoxgloveLiveSummary {
        for entry in rx {
            self.send_unsent();
            match self.send(&entry) {
                true => self.unsent.remove(&entry.key),
                false => self.unsent.insert(entry.key.clone(), entry),
            };
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

    /// Sends to the channel's subscribers; false when it has none.
    fn log(&mut self, channel: &RawChannel, bytes: &[u8], log_time_ns: u64) -> bool {
        if !channel.has_sinks() {
            return false;
        }
        channel.log_with_meta(bytes, PartialMetadata::with_log_time(log_time_ns));
        self.summary.sent += 1;
        true
    }

    /// Whether any of the channels `key`'s messages go to has a subscriber.
    fn watched(&self, key: &str) -> bool {
        let subscribed = |topic: &str| self.by_topic.get(topic).is_some_and(|c| c.has_sinks());
        subscribed(key)
            || self
                .json_topics
                .get(key)
                .is_some_and(|topics| topics.iter().any(|t| subscribed(t)))
    }

    /// Sends the kept entries whose channels have a subscriber now.
    fn send_unsent(&mut self) {
        let ready: Vec<String> = self
            .unsent
            .keys()
            .filter(|key| self.watched(key))
            .cloned()
            .collect();
        for key in ready {
            if let Some(entry) = self.unsent.remove(&key) {
                self.send(&entry);
            }
        }
    }

    /// Converts and sends `entry`; false when it reached no subscriber.
    fn send(&mut self, entry: &Entry) -> bool {
        let flat = Schema::new(SCHEMA_ROOT_NAME, "flatbuffer", SCHEMA_BFBS);
        let mut sent = false;
        if let Some(channel) = self.channel(&entry.key, "flatbuffer", flat) {
            sent |= self.log(&channel, &entry.payload, entry.log_time_ns);
        }
        // Converting costs (images become base64 JSON): only for a first advertisement or a
        // subscribed channel.
        let wanted = match self.json_topics.get(&entry.key) {
            None => true,
            Some(topics) => topics
                .iter()
                .any(|t| self.by_topic.get(t).is_some_and(|c| c.has_sinks())),
        };
        if !wanted {
            return sent;
        }
        let messages = foxglove_messages(&entry.key, &entry.payload);
        let topics = messages.iter().map(|m| m.topic.clone()).collect();
        self.json_topics.insert(entry.key.clone(), topics);
        for m in messages {
            let schema = Schema::new(m.schema, "jsonschema", json_schema(m.schema));
            if let Some(channel) = self.channel(&m.topic, "json", schema) {
                sent |= self.log(&channel, &m.json, entry.log_time_ns);
            }
        }
        sent
    }
}
