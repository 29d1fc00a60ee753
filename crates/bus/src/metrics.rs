//! OpenMetrics on `GET /metrics` for every service started with `--metrics ADDR`, through the
//! `prometheus-client` crate (the Prometheus project's Rust client: its registry, metric types
//! and text encoder, so names, units, `_total` suffixes and escaping follow the standard).
//!
//! A service's counters stay the atomics it already keeps: [`Readings`] reads them when
//! Prometheus scrapes, so nothing on the hot path changes. Histograms (the planner's stage
//! times) are observed where the time is known.

use std::fmt;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::metrics::MetricType;
use prometheus_client::registry::{Registry, Unit};

use crate::Shutdown;

pub use prometheus_client;

/// What a service exposes.
pub trait ServiceMetrics: Send + Sync + 'static {
    /// Registers the service's metrics in `registry` (already prefixed `glasshouse_<kind>_`).
    fn register(self: Arc<Self>, registry: &mut Registry);
    /// The service kind in metric names: `planner`, `detector`, `edge`, `dashboard`.
    fn kind() -> &'static str;
}

type Read = Box<dyn Fn() -> f64 + Send + Sync>;

struct Reading {
    name: &'static str,
    help: &'static str,
    unit: Option<Unit>,
    metric_type: MetricType,
    labels: Vec<(&'static str, String)>,
    read: Read,
}

/// Metrics whose values are read at scrape time. Readings of one name (with different labels)
/// form one family; add them one after another.
#[derive(Default)]
pub struct Readings {
    items: Vec<Reading>,
}

impl fmt::Debug for Readings {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_list()
            .entries(self.items.iter().map(|r| r.name))
            .finish()
    }
}

impl Readings {
    fn push(
        mut self,
        name: &'static str,
        help: &'static str,
        metric_type: MetricType,
        labels: &[(&'static str, &str)],
        read: impl Fn() -> f64 + Send + Sync + 'static,
    ) -> Self {
        self.items.push(Reading {
            name,
            help,
            unit: None,
            metric_type,
            labels: labels.iter().map(|(k, v)| (*k, v.to_string())).collect(),
            read: Box::new(read),
        });
        self
    }

    /// A count that only grows (exposed as `<name>_total`).
    pub fn counter(
        self,
        name: &'static str,
        help: &'static str,
        labels: &[(&'static str, &str)],
        read: impl Fn() -> f64 + Send + Sync + 'static,
    ) -> Self {
        self.push(name, help, MetricType::Counter, labels, read)
    }

    /// A value that goes up and down.
    pub fn gauge(
        self,
        name: &'static str,
        help: &'static str,
        labels: &[(&'static str, &str)],
        read: impl Fn() -> f64 + Send + Sync + 'static,
    ) -> Self {
        self.push(name, help, MetricType::Gauge, labels, read)
    }

    /// The bus messages a service dropped, by reason (`dropped_messages_total{reason=…}`).
    pub fn drops(self, drops: &Arc<crate::DropCounters>) -> Self {
        let read = |field: fn(&crate::DropCounters) -> &AtomicU64| {
            let drops = drops.clone();
            move || field(&drops).load(Ordering::Relaxed) as f64
        };
        let help = "Bus messages dropped, by reason";
        self.counter(
            "dropped_messages",
            help,
            &[("reason", "corrupt")],
            read(|d| &d.corrupt),
        )
        .counter(
            "dropped_messages",
            help,
            &[("reason", "overflow")],
            read(|d| &d.overflow),
        )
        .counter(
            "dropped_messages",
            help,
            &[("reason", "stale_epoch")],
            read(|d| &d.stale_epoch),
        )
    }

    /// The last reading's unit (its name gets the unit's suffix).
    pub fn in_unit(mut self, unit: Unit) -> Self {
        if let Some(last) = self.items.last_mut() {
            last.unit = Some(unit);
        }
        self
    }

    /// Registers the readings, with the process's resident memory.
    pub fn register(self, registry: &mut Registry) {
        registry.register_collector(Box::new(
            self.gauge(
                "process_resident_memory",
                "Resident memory of the process",
                &[],
                || resident_memory_bytes().unwrap_or(0) as f64,
            )
            .in_unit(Unit::Bytes),
        ));
    }
}

impl Collector for Readings {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), fmt::Error> {
        let mut i = 0;
        while i < self.items.len() {
            let first = &self.items[i];
            let family_len = self.items[i..]
                .iter()
                .take_while(|r| r.name == first.name)
                .count();
            let mut family = encoder.encode_descriptor(
                first.name,
                first.help,
                first.unit.as_ref(),
                first.metric_type,
            )?;
            for reading in &self.items[i..i + family_len] {
                let labels: Vec<(&str, &str)> = reading
                    .labels
                    .iter()
                    .map(|(k, v)| (*k, v.as_str()))
                    .collect();
                let metric = family.encode_family(&labels)?;
                let value = (reading.read)();
                match reading.metric_type {
                    MetricType::Counter => ConstCounter::new(value).encode(metric)?,
                    _ => ConstGauge::new(value).encode(metric)?,
                }
            }
            i += family_len;
        }
        Ok(())
    }
}

/// A reading of one atomic counter of a service's counters.
pub fn atomic<K: Send + Sync + 'static>(
    counters: &Arc<K>,
    field: fn(&K) -> &AtomicU64,
) -> impl Fn() -> f64 + Send + Sync + 'static {
    let counters = counters.clone();
    move || field(&counters).load(Ordering::Relaxed) as f64
}

/// A reading of the last status a service kept (0 before the first).
pub fn last<K: Send + Sync + 'static, S: 'static>(
    counters: &Arc<K>,
    status: fn(&K) -> &std::sync::Mutex<Option<S>>,
    read: fn(&S) -> f64,
) -> impl Fn() -> f64 + Send + Sync + 'static {
    let counters = counters.clone();
    move || match status(&counters).lock() {
        Ok(last) => last.as_ref().map_or(0.0, read),
        Err(_) => 0.0,
    }
}

/// The process's resident set size, from `/proc/self/status` (None off Linux).
pub fn resident_memory_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// The registry of a service kind, its metrics prefixed `glasshouse_<kind>_`.
pub fn registry_of<K: ServiceMetrics>(counters: Arc<K>) -> Registry {
    let mut registry = Registry::with_prefix(format!("glasshouse_{}", K::kind()));
    counters.register(&mut registry);
    registry
}

/// The OpenMetrics text of `registry`.
pub fn encode(registry: &Registry) -> String {
    let mut text = String::new();
    if let Err(e) = prometheus_client::encoding::text::encode(&mut text, registry) {
        tracing::warn!("metrics encoding failed: {e}");
    }
    text
}

/// Serves `registry` on `GET /metrics` at `addr` until `shutdown` fires; the bound address.
pub async fn serve(
    addr: &str,
    registry: Registry,
    mut shutdown: Shutdown,
) -> std::io::Result<SocketAddr> {
    let registry = Arc::new(registry);
    let app = axum::Router::new().route(
        "/metrics",
        axum::routing::get(move || {
            let registry = registry.clone();
            async move {
                (
                    [(
                        axum::http::header::CONTENT_TYPE,
                        "application/openmetrics-text; version=1.0.0; charset=utf-8",
                    )],
                    encode(&registry),
                )
            }
        }),
    );
    let listener = tokio::net::TcpListener::bind(addr).await.map_err(|e| {
        std::io::Error::new(e.kind(), format!("metrics: cannot listen on {addr}: {e}"))
    })?;
    let bound = listener.local_addr()?;
    tokio::spawn(async move {
        let stopped = async move { shutdown.wait().await };
        if let Err(e) = axum::serve(listener, app)
            .with_graceful_shutdown(stopped)
            .await
        {
            tracing::warn!("metrics server failed: {e}");
        }
    });
    tracing::info!(%bound, "metrics on http://{bound}/metrics");
    Ok(bound)
}
