//! Who may do what on the bus, for a deployment secured with mutual TLS.
//!
//! A [`Roster`] names every identity (`trolley-t1`, `planner-p1`, `detector-d1`,
//! `dashboard-web1`: the common name of its certificate). From it come the router's access
//! control list ([`acl`]: default deny, by key expression and message type, each identity exactly
//! what its role needs), the router's Zenoh config ([`router_config`]) and one client config per
//! identity ([`client_config`]). Every process is a Zenoh client of the router, so every message
//! passes the router's ACL. Writing keys and certificates is the CLI's job; this crate does no I/O.

mod acl;

use std::path::{Path, PathBuf};

use glasshouse_proto::keys;
use serde_json::{json, Value};

pub use acl::{acl, grants, AclMessage, Flow, Grant};

#[derive(thiserror::Error, Debug, Clone, PartialEq, Eq)]
pub enum TrustError {
    #[error("{0}")]
    Id(#[from] keys::KeyError),
    #[error("{0} is already in the roster")]
    Duplicate(String),
    #[error("router endpoint {0:?} is not tls/HOST:PORT")]
    Endpoint(String),
    #[error("the roster names no router host (the router certificate's names)")]
    NoRouterHost,
    #[error("roster: {0}")]
    Parse(String),
    #[error("install_dir {0:?} is not an absolute path")]
    InstallDir(String),
}

pub type Result<T, E = TrustError> = std::result::Result<T, E>;

/// The role of an identity.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Kind {
    Trolley,
    Planner,
    Detector,
    Dashboard,
}

impl Kind {
    pub const ALL: [Kind; 4] = [
        Kind::Trolley,
        Kind::Planner,
        Kind::Detector,
        Kind::Dashboard,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            Kind::Trolley => "trolley",
            Kind::Planner => "planner",
            Kind::Detector => "detector",
            Kind::Dashboard => "dashboard",
        }
    }
}

/// One process's identity: its role and id. Its certificate's common name is `<kind>-<id>`.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Identity {
    pub kind: Kind,
    pub id: String,
}

impl Identity {
    /// An identity whose id is one key chunk (the id the process uses on the bus).
    pub fn new(kind: Kind, id: &str) -> Result<Self> {
        keys::validate_id(id)?;
        Ok(Self {
            kind,
            id: id.to_owned(),
        })
    }

    /// The certificate's common name, the ACL subject and the stem of its files.
    pub fn common_name(&self) -> String {
        format!("{}-{}", self.kind.as_str(), self.id)
    }
}

/// Every identity of a deployment and where its router is.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Roster {
    #[serde(default)]
    pub trolleys: Vec<String>,
    #[serde(default)]
    pub planners: Vec<String>,
    #[serde(default)]
    pub detectors: Vec<String>,
    #[serde(default)]
    pub dashboards: Vec<String>,
    /// Names the router's certificate is valid for (DNS names or IP addresses).
    #[serde(default = "default_router_hosts")]
    pub router_hosts: Vec<String>,
    /// Where clients connect: `tls/HOST:PORT`; the router listens on that port.
    #[serde(default = "default_router_endpoint")]
    pub router_endpoint: String,
    /// Where the processes read the PKI's files when not where it was made (an absolute path;
    /// the configs name the files there), e.g. `/etc/glasshouse/pki` in a container.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub install_dir: Option<String>,
}

/// The router's certificate names unless the roster says otherwise.
pub fn default_router_hosts() -> Vec<String> {
    ["localhost", "127.0.0.1", "router"]
        .map(String::from)
        .to_vec()
}

/// Where clients connect unless the roster says otherwise.
pub fn default_router_endpoint() -> String {
    "tls/127.0.0.1:7447".to_owned()
}

impl Default for Roster {
    fn default() -> Self {
        Self {
            trolleys: Vec::new(),
            planners: Vec::new(),
            detectors: Vec::new(),
            dashboards: Vec::new(),
            router_hosts: default_router_hosts(),
            router_endpoint: default_router_endpoint(),
            install_dir: None,
        }
    }
}

impl Roster {
    /// Parses and validates a roster file's text (JSON5).
    pub fn parse(text: &str) -> Result<Self> {
        let roster: Roster = json5::from_str(text).map_err(|e| TrustError::Parse(e.to_string()))?;
        roster.validate()?;
        Ok(roster)
    }

    /// The roster as a file (JSON, which JSON5 reads).
    pub fn to_text(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_default() + "\n"
    }

    fn ids(&self, kind: Kind) -> &Vec<String> {
        match kind {
            Kind::Trolley => &self.trolleys,
            Kind::Planner => &self.planners,
            Kind::Detector => &self.detectors,
            Kind::Dashboard => &self.dashboards,
        }
    }

    fn ids_mut(&mut self, kind: Kind) -> &mut Vec<String> {
        match kind {
            Kind::Trolley => &mut self.trolleys,
            Kind::Planner => &mut self.planners,
            Kind::Detector => &mut self.detectors,
            Kind::Dashboard => &mut self.dashboards,
        }
    }

    /// Every identity, trolleys first.
    pub fn identities(&self) -> Vec<Identity> {
        Kind::ALL
            .into_iter()
            .flat_map(|kind| {
                self.ids(kind).iter().map(move |id| Identity {
                    kind,
                    id: id.clone(),
                })
            })
            .collect()
    }

    pub fn contains(&self, identity: &Identity) -> bool {
        self.ids(identity.kind).contains(&identity.id)
    }

    /// Adds an identity; one already there is an error (its key would be replaced).
    pub fn add(&mut self, identity: &Identity) -> Result<()> {
        if self.contains(identity) {
            return Err(TrustError::Duplicate(identity.common_name()));
        }
        self.ids_mut(identity.kind).push(identity.id.clone());
        Ok(())
    }

    /// Ids are key chunks, no identity twice, a `tls/HOST:PORT` endpoint, a router host.
    pub fn validate(&self) -> Result<()> {
        let mut seen = std::collections::BTreeSet::new();
        for identity in self.identities() {
            keys::validate_id(&identity.id)?;
            if !seen.insert(identity.common_name()) {
                return Err(TrustError::Duplicate(identity.common_name()));
            }
        }
        if self.router_hosts.is_empty() {
            return Err(TrustError::NoRouterHost);
        }
        if let Some(dir) = &self.install_dir {
            if !Path::new(dir).is_absolute() {
                return Err(TrustError::InstallDir(dir.clone()));
            }
        }
        self.router_port().map(|_| ())
    }

    /// Where the configs name the files: [`Roster::install_dir`], else where they are made.
    pub fn installed(&self, made: &Layout) -> Layout {
        match &self.install_dir {
            Some(dir) => Layout::new(Path::new(dir)),
            None => made.clone(),
        }
    }

    /// The port of [`Roster::router_endpoint`].
    pub fn router_port(&self) -> Result<u16> {
        let bad = || TrustError::Endpoint(self.router_endpoint.clone());
        let address = self.router_endpoint.strip_prefix("tls/").ok_or_else(bad)?;
        let (host, port) = address.rsplit_once(':').ok_or_else(bad)?;
        if host.is_empty() {
            return Err(bad());
        }
        port.parse().map_err(|_| bad())
    }

    /// Where the router listens: every interface, on the endpoint's port.
    pub fn router_listen(&self) -> Result<String> {
        Ok(format!("tls/0.0.0.0:{}", self.router_port()?))
    }
}

/// Where the files of a deployment's PKI live in its directory.
#[derive(Clone, Debug)]
pub struct Layout {
    pub dir: PathBuf,
}

/// The stem of the router's files.
pub const ROUTER: &str = "router";

impl Layout {
    pub fn new(dir: &Path) -> Self {
        Self {
            dir: dir.to_path_buf(),
        }
    }

    pub fn ca_cert(&self) -> PathBuf {
        self.dir.join("ca.pem")
    }

    pub fn ca_key(&self) -> PathBuf {
        self.dir.join("ca.key")
    }

    pub fn roster(&self) -> PathBuf {
        self.dir.join("roster.json5")
    }

    /// `<stem>.pem`: the certificate of the router or an identity (stem = common name).
    pub fn cert(&self, stem: &str) -> PathBuf {
        self.dir.join(format!("{stem}.pem"))
    }

    /// `<stem>.key`: its private key.
    pub fn key(&self, stem: &str) -> PathBuf {
        self.dir.join(format!("{stem}.key"))
    }

    /// `<stem>.json5`: its Zenoh config.
    pub fn config(&self, stem: &str) -> PathBuf {
        self.dir.join(format!("{stem}.json5"))
    }
}

fn path_text(path: &Path) -> String {
    path.to_string_lossy().into_owned()
}

/// Bytes above the largest protocol message that a Zenoh message may add (headers, attachment).
pub const MESSAGE_HEADROOM_BYTES: usize = 1 << 20;

/// The largest message the router's transport reassembles: the largest payload the protocol
/// accepts ([`glasshouse_proto::max_bytes_any`], a map snapshot it forwards between planners)
/// plus headroom. Larger ones are dropped on receipt.
pub fn max_message_bytes() -> usize {
    glasshouse_proto::max_bytes_any() + MESSAGE_HEADROOM_BYTES
}

/// The largest message `kind`'s transport reassembles: the largest payload its role receives,
/// plus headroom. A trolley takes only views, a detector frames; a dashboard everything but
/// snapshots; a planner snapshots too. An oversized put that the ACL lets through on the way
/// (a trolley's own frame of 50 MB) is dropped by each receiver's transport before a service
/// copies it.
pub fn max_message_bytes_for(kind: Kind) -> usize {
    use glasshouse_proto::MessageKind as M;
    let largest = |kinds: &[M]| kinds.iter().map(|m| m.max_bytes()).max().unwrap_or(0);
    let received = match kind {
        Kind::Trolley => largest(&[M::RankedViews]),
        Kind::Detector => largest(&[M::RgbdFrame]),
        Kind::Dashboard => largest(
            &M::ALL
                .into_iter()
                .filter(|&m| m != M::MapSnapshot)
                .collect::<Vec<_>>(),
        ),
        Kind::Planner => glasshouse_proto::max_bytes_any(),
    };
    received + MESSAGE_HEADROOM_BYTES
}

/// Link lease of every deployed process, ms. A link silent this long is dropped with its
/// liveliness tokens, so this is how long a hung planner or a cut cable keeps its trolleys
/// (Zenoh's default is 10 s). Trolleys roam between a glasshouse's Wi-Fi access points along
/// their rails, and a handover without fast roaming takes up to about 2 s: 3 s rides one out
/// without moving a trolley to another planner, and a planner that stops answering loses its
/// trolleys a third as late as with the default.
pub const LAN_LEASE_MS: u64 = 3_000;

/// Keep-alives per lease: a keep-alive every 750 ms, so three may be lost before the lease ends.
pub const LAN_KEEP_ALIVES: u64 = 4;

/// The `transport/link/tx` section of every deployed config.
fn lan_tx() -> Value {
    json!({ "lease": LAN_LEASE_MS, "keep_alive": LAN_KEEP_ALIVES })
}

/// The router's Zenoh config: an mTLS listener, the roster's ACL, bounded messages.
pub fn router_config(roster: &Roster, layout: &Layout) -> Result<Value> {
    Ok(json!({
        "mode": "router",
        "listen": { "endpoints": [roster.router_listen()?] },
        "scouting": { "multicast": { "enabled": false } },
        "transport": { "link": {
            "tls": {
                "root_ca_certificate": path_text(&layout.ca_cert()),
                "listen_private_key": path_text(&layout.key(ROUTER)),
                "listen_certificate": path_text(&layout.cert(ROUTER)),
                "enable_mtls": true,
            },
            "rx": { "max_message_size": max_message_bytes() },
            "tx": lan_tx(),
        } },
        "access_control": acl(roster),
    }))
}

/// An identity's Zenoh config: a client of the router over mTLS with its own key and
/// certificate, bounded messages.
pub fn client_config(roster: &Roster, identity: &Identity, layout: &Layout) -> Value {
    let stem = identity.common_name();
    json!({
        "mode": "client",
        "connect": { "endpoints": [roster.router_endpoint] },
        "scouting": { "multicast": { "enabled": false } },
        "transport": { "link": {
            "tls": {
                "root_ca_certificate": path_text(&layout.ca_cert()),
                "connect_private_key": path_text(&layout.key(&stem)),
                "connect_certificate": path_text(&layout.cert(&stem)),
                "enable_mtls": true,
            },
            "rx": { "max_message_size": max_message_bytes_for(identity.kind) },
            "tx": lan_tx(),
        } },
    })
}

/// A config as a file's text, with a first line saying what it is.
pub fn config_text(what: &str, config: &Value) -> String {
    let body = serde_json::to_string_pretty(config).unwrap_or_default();
    format!("// {what}. Generated by `glasshouse secure`; regenerated by `secure issue`.\n{body}\n")
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) fn roster() -> Roster {
        Roster::parse(
            r#"{ trolleys: ["t1", "t2"], planners: ["p1", "p2"], detectors: ["d1"],
                 dashboards: ["web1"], router_endpoint: "tls/127.0.0.1:7448" }"#,
        )
        .expect("valid roster")
    }

    #[test]
    fn a_roster_names_identities_by_common_name() {
        let names: Vec<String> = roster()
            .identities()
            .iter()
            .map(Identity::common_name)
            .collect();
        assert_eq!(
            names,
            [
                "trolley-t1",
                "trolley-t2",
                "planner-p1",
                "planner-p2",
                "detector-d1",
                "dashboard-web1"
            ]
        );
        assert_eq!(roster().router_hosts, default_router_hosts());
        assert_eq!(roster().router_listen().expect("port"), "tls/0.0.0.0:7448");
    }

    #[test]
    fn bad_rosters_are_refused() {
        let dup = r#"{ trolleys: ["t1", "t1"] }"#;
        assert_eq!(
            Roster::parse(dup),
            Err(TrustError::Duplicate("trolley-t1".into()))
        );
        assert!(matches!(
            Roster::parse(r#"{ planners: ["a/b"] }"#),
            Err(TrustError::Id(_))
        ));
        for endpoint in [
            "tcp/router:7447",
            "tls/router",
            "tls/:7447",
            "tls/router:port",
        ] {
            let text = format!(r#"{{ trolleys: ["t1"], router_endpoint: "{endpoint}" }}"#);
            assert!(
                matches!(Roster::parse(&text), Err(TrustError::Endpoint(_))),
                "{endpoint}"
            );
        }
        assert!(matches!(
            Roster::parse(r#"{ robots: ["t1"] }"#),
            Err(TrustError::Parse(_))
        ));
        assert_eq!(
            Roster::parse(r#"{ router_hosts: [] }"#),
            Err(TrustError::NoRouterHost)
        );
    }

    #[test]
    fn adding_an_identity_twice_is_refused_and_the_roster_round_trips() {
        let mut r = roster();
        let t3 = Identity::new(Kind::Trolley, "t3").expect("valid");
        r.add(&t3).expect("new identity");
        assert!(r.contains(&t3));
        assert_eq!(r.add(&t3), Err(TrustError::Duplicate("trolley-t3".into())));
        assert_eq!(Roster::parse(&r.to_text()).expect("round trip"), r);
        assert!(Identity::new(Kind::Dashboard, "").is_err());
    }

    #[test]
    fn configs_name_the_files_where_they_are_installed() {
        let made = Layout::new(Path::new("/tmp/pki"));
        let mut roster = roster();
        assert_eq!(roster.installed(&made).dir, made.dir);
        roster.install_dir = Some("/etc/glasshouse/pki".into());
        let text = roster.to_text();
        assert_eq!(Roster::parse(&text), Ok(roster.clone()));
        let installed = roster.installed(&made);
        let t1 = Identity::new(Kind::Trolley, "t1").expect("valid");
        let config = client_config(&roster, &t1, &installed);
        assert_eq!(
            config["transport"]["link"]["tls"]["connect_private_key"],
            "/etc/glasshouse/pki/trolley-t1.key"
        );
        roster.install_dir = Some("relative/pki".into());
        assert_eq!(
            roster.validate(),
            Err(TrustError::InstallDir("relative/pki".into()))
        );
    }

    #[test]
    fn configs_use_mutual_tls_and_bound_messages() {
        let layout = Layout::new(Path::new("/pki"));
        let r = roster();
        let t1 = Identity::new(Kind::Trolley, "t1").expect("valid");
        let client = client_config(&r, &t1, &layout);
        assert_eq!(client["mode"], "client");
        assert_eq!(
            client["connect"]["endpoints"],
            json!(["tls/127.0.0.1:7448"])
        );
        let tls = &client["transport"]["link"]["tls"];
        assert_eq!(tls["enable_mtls"], true);
        assert_eq!(tls["connect_private_key"], "/pki/trolley-t1.key");
        assert_eq!(tls["connect_certificate"], "/pki/trolley-t1.pem");
        assert_eq!(tls["root_ca_certificate"], "/pki/ca.pem");
        let router = router_config(&r, &layout).expect("valid");
        assert_eq!(router["listen"]["endpoints"], json!(["tls/0.0.0.0:7448"]));
        assert_eq!(
            router["transport"]["link"]["tls"]["listen_private_key"],
            "/pki/router.key"
        );
        assert_eq!(router["access_control"]["default_permission"], "deny");
        for config in [&client, &router] {
            let tx = &config["transport"]["link"]["tx"];
            assert_eq!(
                tx["lease"],
                json!(LAN_LEASE_MS),
                "a LAN lease, not Zenoh's 10 s"
            );
            assert_eq!(tx["keep_alive"], json!(LAN_KEEP_ALIVES));
        }
        let max = router["transport"]["link"]["rx"]["max_message_size"]
            .as_u64()
            .expect("a size");
        assert!(max as usize > glasshouse_proto::max_bytes_any());
        assert!(max < 1 << 30, "below Zenoh's default of 1 GiB");
        let rx_max = |kind: Kind| {
            let id = Identity::new(kind, "x").expect("valid");
            let config = client_config(&r, &id, &layout);
            config["transport"]["link"]["rx"]["max_message_size"]
                .as_u64()
                .expect("a size") as usize
        };
        let headroom = MESSAGE_HEADROOM_BYTES;
        assert_eq!(rx_max(Kind::Trolley), 256 * 1024 + headroom, "views only");
        assert_eq!(rx_max(Kind::Detector), 8 * 1024 * 1024 + headroom, "frames");
        assert_eq!(
            rx_max(Kind::Dashboard),
            64 * 1024 * 1024 + headroom,
            "map updates"
        );
        assert_eq!(rx_max(Kind::Planner), max_message_bytes(), "snapshots");
        let text = config_text("router", &router);
        assert!(text.starts_with("// router."));
        let parsed: Value = json5::from_str(&text).expect("the file reads back as JSON5");
        assert_eq!(parsed, router);
    }
}
