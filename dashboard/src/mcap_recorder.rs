//! MCAP recordings of the bus: every Glasshouse key as a `flatbuffer` channel (the envelope as
//! it travelled, with the schema's `.bfbs`), plus the same content in Foxglove's well-known
//! schemas ([`crate::foxglove`]). Files rotate by size and by duration; each begins with the
//! run's metadata. Writing happens on its own thread behind a bounded queue: a recorder that
//! cannot keep up drops (and counts) messages instead of slowing the dashboard.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Instant;

use anyhow::Context;
use glasshouse_proto::{keys, SCHEMA_BFBS, SCHEMA_ROOT_NAME};
use serde::Deserialize;

use crate::foxglove;

/// Where and how to record.
#[derive(Clone, Debug, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct McapSettings {
    /// The folder the files go to (created when missing).
    pub dir: PathBuf,
    /// A file is closed and the next one begun past this many bytes of messages.
    pub max_file_bytes: u64,
    /// ... or after this many seconds.
    pub max_file_s: u64,
    /// Also write Foxglove's well-known schemas (images, clouds, scenes, transforms).
    pub foxglove: bool,
    /// Messages waiting for the writer before new ones are dropped.
    pub queue: usize,
}

impl Default for McapSettings {
    fn default() -> Self {
        Self {
            dir: PathBuf::from("recordings"),
            max_file_bytes: 2 << 30,
            max_file_s: 600,
            foxglove: true,
            queue: 1024,
        }
    }
}

/// What a recording wrote.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct McapSummary {
    pub files: Vec<PathBuf>,
    /// Bus messages recorded (each once on its flatbuffer channel).
    pub messages: u64,
    /// Of which RGB-D frames.
    pub frames: u64,
    /// Bytes written to disk over all files.
    pub disk_bytes: u64,
    /// Messages the writer could not take in time.
    pub dropped: u64,
}

struct Entry {
    key: String,
    payload: Vec<u8>,
    log_time_ns: u64,
}

/// A recording in progress.
pub struct McapRecorder {
    tx: Option<SyncSender<Entry>>,
    thread: Option<JoinHandle<anyhow::Result<McapSummary>>>,
    dropped: Arc<AtomicU64>,
}

impl McapRecorder {
    /// Creates the folder and starts the writer; `run` is written as metadata into every file.
    pub fn start(settings: McapSettings, run: BTreeMap<String, String>) -> anyhow::Result<Self> {
        std::fs::create_dir_all(&settings.dir)
            .with_context(|| format!("cannot create {}", settings.dir.display()))?;
        anyhow::ensure!(
            settings.max_file_bytes > 0 && settings.max_file_s > 0,
            "file limits must be > 0"
        );
        let (tx, rx) = sync_channel(settings.queue.max(1));
        let mut writer = RotatingWriter::new(settings, run);
        writer.open_next()?;
        let thread = std::thread::Builder::new()
            .name("mcap-writer".into())
            .spawn(move || writer.run(rx))?;
        Ok(Self {
            tx: Some(tx),
            thread: Some(thread),
            dropped: Arc::new(AtomicU64::new(0)),
        })
    }

    /// Queues the verified envelope `payload` that arrived on `key` at `log_time_ns`.
    pub fn record(&self, key: &str, payload: Vec<u8>, log_time_ns: u64) {
        let Some(tx) = &self.tx else { return };
        let entry = Entry {
            key: key.to_string(),
            payload,
            log_time_ns,
        };
        if let Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) = tx.try_send(entry) {
            let n = self.dropped.fetch_add(1, Ordering::Relaxed) + 1;
            if n <= 5 || n.is_multiple_of(100) {
                tracing::warn!(
                    dropped = n,
                    "the MCAP writer cannot keep up: message dropped"
                );
            }
        }
    }

    /// Messages dropped so far.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Writes what is queued, closes the last file and says what was written.
    pub fn finish(mut self) -> anyhow::Result<McapSummary> {
        drop(self.tx.take());
        let thread = self.thread.take().context("recorder already finished")?;
        let mut summary = thread
            .join()
            .map_err(|_| anyhow::anyhow!("the MCAP writer panicked"))??;
        summary.dropped = self.dropped();
        Ok(summary)
    }
}

type McapWriter = mcap::Writer<BufWriter<File>>;

struct OpenFile {
    path: PathBuf,
    writer: McapWriter,
    /// Channel id by topic, and schema id by name, of this file.
    channels: HashMap<String, u16>,
    schemas: HashMap<&'static str, u16>,
    bytes: u64,
    opened: Instant,
}

struct RotatingWriter {
    settings: McapSettings,
    run: BTreeMap<String, String>,
    file: Option<OpenFile>,
    summary: McapSummary,
    sequence: u32,
}

impl RotatingWriter {
    fn new(settings: McapSettings, run: BTreeMap<String, String>) -> Self {
        Self {
            settings,
            run,
            file: None,
            summary: McapSummary::default(),
            sequence: 0,
        }
    }

    fn run(mut self, rx: Receiver<Entry>) -> anyhow::Result<McapSummary> {
        while let Ok(entry) = rx.recv() {
            if let Err(e) = self.write(&entry) {
                tracing::error!(key = %entry.key, "cannot record: {e:#}");
            }
        }
        self.close()?;
        Ok(self.summary)
    }

    fn file_path(&self) -> PathBuf {
        let run_id = self.run.get("run_id").map_or("run", String::as_str);
        self.settings
            .dir
            .join(format!("{run_id}-{:04}.mcap", self.summary.files.len()))
    }

    fn open_next(&mut self) -> anyhow::Result<()> {
        self.close()?;
        let path = self.file_path();
        let file =
            File::create(&path).with_context(|| format!("cannot create {}", path.display()))?;
        let mut writer = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .profile("glasshouse")
            .library(concat!("glasshouse ", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::new(file))?;
        let mut metadata = self.run.clone();
        metadata.insert("file_index".into(), self.summary.files.len().to_string());
        writer.write_metadata(&mcap::records::Metadata {
            name: "glasshouse_run".into(),
            metadata,
        })?;
        tracing::info!(file = %path.display(), "recording to MCAP");
        self.summary.files.push(path.clone());
        self.file = Some(OpenFile {
            path,
            writer,
            channels: HashMap::new(),
            schemas: HashMap::new(),
            bytes: 0,
            opened: Instant::now(),
        });
        Ok(())
    }

    fn close(&mut self) -> anyhow::Result<()> {
        if let Some(mut file) = self.file.take() {
            file.writer.finish()?;
            drop(file.writer);
            let size = std::fs::metadata(&file.path).map(|m| m.len()).unwrap_or(0);
            self.summary.disk_bytes += size;
        }
        Ok(())
    }

    fn write(&mut self, entry: &Entry) -> anyhow::Result<()> {
        let full = self.file.as_ref().is_none_or(|f| {
            f.bytes >= self.settings.max_file_bytes
                || f.opened.elapsed().as_secs() >= self.settings.max_file_s
        });
        if full {
            self.open_next()?;
        }
        let foxglove = if self.settings.foxglove {
            foxglove_messages(&entry.key, &entry.payload)
        } else {
            Vec::new()
        };
        let file = self.file.as_mut().context("no open file")?;
        self.sequence = self.sequence.wrapping_add(1);
        let (sequence, log_time) = (self.sequence, entry.log_time_ns);
        file.write(
            &entry.key,
            SCHEMA_ROOT_NAME,
            Schema::Flatbuffer,
            &entry.payload,
            sequence,
            log_time,
        )?;
        for m in foxglove {
            file.write(
                &m.topic,
                m.schema,
                Schema::Json,
                &m.json,
                sequence,
                log_time,
            )?;
        }
        self.summary.messages += 1;
        if entry.key.ends_with("/rgbd") {
            self.summary.frames += 1;
        }
        Ok(())
    }
}

#[derive(Clone, Copy)]
enum Schema {
    Flatbuffer,
    Json,
}

impl OpenFile {
    fn channel(&mut self, topic: &str, schema: &'static str, kind: Schema) -> anyhow::Result<u16> {
        if let Some(id) = self.channels.get(topic) {
            return Ok(*id);
        }
        let schema_id = match self.schemas.get(schema) {
            Some(id) => *id,
            None => {
                let id = match kind {
                    Schema::Flatbuffer => {
                        self.writer.add_schema(schema, "flatbuffer", SCHEMA_BFBS)?
                    }
                    Schema::Json => self.writer.add_schema(
                        schema,
                        "jsonschema",
                        &foxglove::json_schema(schema),
                    )?,
                };
                self.schemas.insert(schema, id);
                id
            }
        };
        let encoding = match kind {
            Schema::Flatbuffer => "flatbuffer",
            Schema::Json => "json",
        };
        let id = self
            .writer
            .add_channel(schema_id, topic, encoding, &BTreeMap::new())?;
        self.channels.insert(topic.to_string(), id);
        Ok(id)
    }

    fn write(
        &mut self,
        topic: &str,
        schema: &'static str,
        kind: Schema,
        data: &[u8],
        sequence: u32,
        log_time: u64,
    ) -> anyhow::Result<()> {
        let channel_id = self.channel(topic, schema, kind)?;
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence,
            log_time,
            publish_time: log_time,
        };
        self.writer.write_to_known_channel(&header, data)?;
        self.bytes += data.len() as u64;
        Ok(())
    }
}

/// The Foxglove form of an envelope that arrived on `key` (none when it does not decode: the
/// bus verified it, so that does not happen for what the dashboard hears).
pub(crate) fn foxglove_messages(key: &str, payload: &[u8]) -> Vec<foxglove::FoxgloveMessage> {
    let (Some(parsed), Ok((header, message))) =
        (keys::parse(key), glasshouse_proto::decode(payload))
    else {
        return Vec::new();
    };
    foxglove::convert(&parsed, &header, &message)
}

/// The run's metadata: an id from the start time, the version, and what the caller adds.
pub fn run_metadata(started_ns: u64, extra: &[(&str, String)]) -> BTreeMap<String, String> {
    let mut run = BTreeMap::new();
    run.insert(
        "run_id".into(),
        format!("glasshouse-{}", started_ns / 1_000_000),
    );
    run.insert("started_ns".into(), started_ns.to_string());
    run.insert(
        "glasshouse_version".into(),
        env!("CARGO_PKG_VERSION").into(),
    );
    for (k, v) in extra {
        run.insert((*k).to_string(), v.clone());
    }
    run
}

/// The files of a recording folder, in order.
pub fn recording_files(dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("cannot list {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    files.sort();
    Ok(files)
}
