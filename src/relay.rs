//! `glasshouse relay`: a TCP relay that can cut a link the way a failed switch or a pulled cable
//! does, for rehearsing network partitions on one machine without privileges.
//!
//! A process connects to the relay's listen address instead of the router's; every connection is
//! forwarded to `--to` (TCP, or TLS carried through unread). SIGUSR1 cuts: bytes stop flowing both ways, but no connection is closed
//! (no FIN, no RST), so each side learns of the cut only when its Zenoh lease expires, as it would
//! behind a dead link. New connections are accepted and held, not forwarded, while cut. SIGUSR2
//! heals: held bytes and connections flow again. SIGTERM or Ctrl-C stops the relay.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use anyhow::Context;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::signal::unix::{signal, SignalKind};
use tokio::sync::watch;

#[derive(clap::Args, Debug)]
pub struct RelayArgs {
    /// Address to listen on (host:port, or a Zenoh endpoint such as tcp/127.0.0.1:7450).
    #[arg(long, value_name = "ADDR")]
    pub listen: String,
    /// Address every connection is forwarded to (host:port or tcp/host:port).
    #[arg(long, value_name = "ADDR")]
    pub to: String,
}

/// The TCP address of a Zenoh `tcp/` or `tls/` endpoint (TLS passes through untouched), or the
/// address itself.
fn socket_address(addr: &str) -> anyhow::Result<String> {
    match addr.split_once('/') {
        None => Ok(addr.to_owned()),
        Some(("tcp" | "tls", rest)) => Ok(rest.to_owned()),
        Some((proto, _)) => anyhow::bail!("the relay forwards TCP only, not {proto}: {addr}"),
    }
}

/// Bytes relayed, for the log when the relay stops.
#[derive(Default)]
struct Relayed {
    connections: AtomicU64,
    bytes: AtomicU64,
}

pub async fn run(args: RelayArgs) -> anyhow::Result<()> {
    let listen = socket_address(&args.listen)?;
    let to = socket_address(&args.to)?;
    let listener = TcpListener::bind(&listen)
        .await
        .with_context(|| format!("cannot listen on {listen}"))?;
    let (cut_tx, cut_rx) = watch::channel(false);
    let relayed = Arc::new(Relayed::default());
    tracing::info!(%listen, %to, "relay up (SIGUSR1 cuts, SIGUSR2 heals)");
    let mut cut_signal = signal(SignalKind::user_defined1())?;
    let mut heal_signal = signal(SignalKind::user_defined2())?;
    let shutdown = glasshouse_bus::shutdown_signal();
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            accepted = listener.accept() => {
                let (inbound, peer) = accepted.context("accept")?;
                relayed.connections.fetch_add(1, Ordering::Relaxed);
                tracing::info!(%peer, "connection");
                tokio::spawn(forward(inbound, to.clone(), cut_rx.clone(), relayed.clone()));
            }
            _ = cut_signal.recv() => {
                cut_tx.send_replace(true);
                tracing::info!("cut: no byte passes until SIGUSR2");
            }
            _ = heal_signal.recv() => {
                cut_tx.send_replace(false);
                tracing::info!("healed");
            }
            _ = &mut shutdown => break,
        }
    }
    tracing::info!(
        connections = relayed.connections.load(Ordering::Relaxed),
        bytes = relayed.bytes.load(Ordering::Relaxed),
        "relay stopped"
    );
    Ok(())
}

/// Waits while the link is cut.
async fn wait_healed(cut: &mut watch::Receiver<bool>) -> bool {
    cut.wait_for(|cut| !cut).await.is_ok()
}

/// One connection: connects upstream once the link is up, then copies both ways.
async fn forward(
    inbound: TcpStream,
    to: String,
    mut cut: watch::Receiver<bool>,
    relayed: Arc<Relayed>,
) {
    if !wait_healed(&mut cut).await {
        return;
    }
    let upstream = match TcpStream::connect(&to).await {
        Ok(s) => s,
        Err(e) => {
            tracing::warn!(%to, error = %e, "cannot reach the relay's target");
            return;
        }
    };
    let _ = inbound.set_nodelay(true);
    let _ = upstream.set_nodelay(true);
    let (in_read, in_write) = inbound.into_split();
    let (up_read, up_write) = upstream.into_split();
    let there = copy(in_read, up_write, cut.clone(), relayed.clone());
    let back = copy(up_read, in_write, cut, relayed);
    // Either side closing ends the connection (a real close, which the peer sees).
    tokio::select! {
        _ = there => {}
        _ = back => {}
    }
}

/// Copies `from` to `to`; while cut, neither reads nor writes, so the sender's buffers fill as
/// behind a dead link.
async fn copy(
    mut from: tokio::net::tcp::OwnedReadHalf,
    mut to: tokio::net::tcp::OwnedWriteHalf,
    mut cut: watch::Receiver<bool>,
    relayed: Arc<Relayed>,
) {
    let mut buffer = vec![0u8; 64 * 1024];
    loop {
        if !wait_healed(&mut cut).await {
            return;
        }
        let n = match from.read(&mut buffer).await {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        // Bytes read just before a cut are held until it heals.
        if !wait_healed(&mut cut).await || to.write_all(&buffer[..n]).await.is_err() {
            return;
        }
        relayed.bytes.fetch_add(n as u64, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_and_plain_addresses_are_read_and_others_refused() {
        assert_eq!(
            socket_address("tcp/127.0.0.1:7447").expect("an address"),
            "127.0.0.1:7447"
        );
        assert_eq!(
            socket_address("127.0.0.1:7447").expect("an address"),
            "127.0.0.1:7447"
        );
        assert_eq!(
            socket_address("tls/127.0.0.1:7447").expect("an address"),
            "127.0.0.1:7447"
        );
        assert!(socket_address("udp/127.0.0.1:7447").is_err());
    }
}
