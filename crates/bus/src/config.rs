//! The Zenoh configuration of a process, in three layers: the project's defaults, then the
//! `--zenoh-config` file merged over them, then the flags actually given.
//!
//! The layers are merged as JSON trees (objects merge key by key, anything else replaces), so a
//! file that sets TLS keeps multicast off, clients retrying forever and the long
//! block-before-close, and a file's endpoints stay unless a flag names others.

use serde_json::{json, Map, Value};

use crate::{BusArgs, BusError, Result};

/// The project's defaults, under any file and flag.
pub fn project_defaults() -> Value {
    json!({
        "scouting": { "multicast": { "enabled": false } },
        "connect": {
            // Containers start in any order: clients keep retrying instead of exiting.
            "timeout_ms": { "router": -1, "peer": -1, "client": -1 },
            "exit_on_failure": { "router": false, "peer": false, "client": false },
            // A client that lost its router tries again within a second (Zenoh's default backs
            // off to 4 s): a restarted router, or the second one, has the fleet back sooner.
            "retry": { "period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2 },
        },
        "transport": { "link": { "tx": { "queue": { "congestion_control": { "block": {
            // A busy consumer must slow a reliable producer down, not get its link closed.
            "wait_before_close": 60_000_000
        } } } } } },
    })
}

/// Merges `over` into `base`: objects key by key, any other value replaces.
pub fn merge(base: &mut Value, over: Value) {
    match (base, over) {
        (Value::Object(base), Value::Object(over)) => {
            for (key, value) in over {
                match base.get_mut(&key) {
                    Some(slot) => merge(slot, value),
                    None => {
                        base.insert(key, value);
                    }
                }
            }
        }
        (base, over) => *base = over,
    }
}

/// Sets `value` at a `/`-separated path, creating the objects on the way.
fn set_path(tree: &mut Value, path: &str, value: Value) {
    let mut over = value;
    for key in path.rsplit('/') {
        let mut object = Map::new();
        object.insert(key.to_owned(), over);
        over = Value::Object(object);
    }
    merge(tree, over);
}

/// The flags that were given, as a tree to merge over the file.
fn flag_layer(args: &BusArgs) -> Value {
    let mut flags = json!({});
    if let Some(mode) = args.mode {
        set_path(&mut flags, "mode", json!(mode.as_str()));
    }
    if !args.connect.is_empty() {
        set_path(&mut flags, "connect/endpoints", json!(args.connect));
    }
    if !args.listen.is_empty() {
        set_path(&mut flags, "listen/endpoints", json!(args.listen));
    }
    if let Some(lease_ms) = args.lease_ms {
        set_path(&mut flags, "transport/link/tx/lease", json!(lease_ms));
        // Four keep-alives per lease, as Zenoh's default.
        set_path(&mut flags, "transport/link/tx/keep_alive", json!(4));
    }
    flags
}

/// Reads a Zenoh configuration file (JSON5, Zenoh's own format) as a tree.
pub fn read_config_file(path: &std::path::Path) -> Result<Value> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| BusError::Config(format!("{}: {e}", path.display())))?;
    json5::from_str(&text).map_err(|e| BusError::Config(format!("{}: {e}", path.display())))
}

/// The merged tree: defaults, then `file`, then the flags; `default_listen` applies only when
/// neither the file nor a flag names a listen endpoint.
pub fn config_tree(args: &BusArgs, file: Option<Value>, default_listen: Option<&str>) -> Value {
    let mut tree = project_defaults();
    if let Some(file) = file {
        merge(&mut tree, file);
    }
    merge(&mut tree, flag_layer(args));
    let has_listen = tree.pointer("/listen/endpoints").is_some_and(|e| match e {
        Value::Array(list) => !list.is_empty(),
        Value::Null => false,
        _ => true,
    });
    if let (false, Some(endpoint)) = (has_listen, default_listen) {
        set_path(&mut tree, "listen/endpoints", json!([endpoint]));
    }
    tree
}

fn build(args: &BusArgs, default_listen: Option<&str>) -> Result<zenoh::Config> {
    let file = match &args.zenoh_config {
        Some(path) => Some(read_config_file(path)?),
        None => None,
    };
    let tree = config_tree(args, file, default_listen);
    let source = args
        .zenoh_config
        .as_ref()
        .map_or_else(|| "flags".to_owned(), |p| p.display().to_string());
    zenoh::Config::from_json5(&tree.to_string())
        .map_err(|e| BusError::Config(format!("{source}: {e}")))
}

/// Builds the Zenoh configuration from the shared flags: the project's defaults, then the
/// `--zenoh-config` file, then the flags given.
pub fn zenoh_config(args: &BusArgs) -> Result<zenoh::Config> {
    build(args, None)
}

/// Like [`zenoh_config`] for a router: mode router, and `default_listen` when neither the file
/// nor a flag names a listen endpoint.
pub fn router_config(args: &BusArgs, default_listen: &str) -> Result<zenoh::Config> {
    let args = BusArgs {
        mode: Some(crate::Mode::Router),
        ..args.clone()
    };
    build(&args, Some(default_listen))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Mode;

    fn file() -> Value {
        json5::from_str(
            r#"{
                mode: "client",
                connect: { endpoints: ["tls/router:7447"] },
                listen: { endpoints: ["tls/0.0.0.0:7448"] },
                transport: { link: { tls: { enable_mtls: true }, tx: { lease: 3000 } } },
            }"#,
        )
        .expect("test file parses")
    }

    #[test]
    fn a_file_keeps_the_project_defaults_it_does_not_set() {
        let tree = config_tree(&BusArgs::default(), Some(file()), None);
        assert_eq!(tree["scouting"]["multicast"]["enabled"], json!(false));
        assert_eq!(tree["connect"]["timeout_ms"]["client"], json!(-1));
        assert_eq!(
            tree["transport"]["link"]["tx"]["queue"]["congestion_control"]["block"]
                ["wait_before_close"],
            json!(60_000_000)
        );
        assert_eq!(tree["transport"]["link"]["tls"]["enable_mtls"], json!(true));
        assert_eq!(tree["transport"]["link"]["tx"]["lease"], json!(3000));
        assert_eq!(tree["connect"]["endpoints"], json!(["tls/router:7447"]));
        assert_eq!(tree["mode"], json!("client"));
    }

    #[test]
    fn a_file_overrides_a_default() {
        let over = json!({ "scouting": { "multicast": { "enabled": true } },
                           "connect": { "timeout_ms": 5000 } });
        let tree = config_tree(&BusArgs::default(), Some(over), None);
        assert_eq!(tree["scouting"]["multicast"]["enabled"], json!(true));
        assert_eq!(tree["connect"]["timeout_ms"], json!(5000));
        assert_eq!(tree["connect"]["exit_on_failure"]["client"], json!(false));
    }

    #[test]
    fn given_flags_override_the_file_and_absent_ones_do_not() {
        let args = BusArgs {
            connect: vec!["tls/127.0.0.1:9000".into()],
            mode: Some(Mode::Peer),
            lease_ms: Some(1000),
            ..BusArgs::default()
        };
        let tree = config_tree(&args, Some(file()), None);
        assert_eq!(tree["connect"]["endpoints"], json!(["tls/127.0.0.1:9000"]));
        assert_eq!(tree["listen"]["endpoints"], json!(["tls/0.0.0.0:7448"]));
        assert_eq!(tree["mode"], json!("peer"));
        assert_eq!(tree["transport"]["link"]["tx"]["lease"], json!(1000));
        assert_eq!(tree["transport"]["link"]["tls"]["enable_mtls"], json!(true));
    }

    #[test]
    fn the_default_listener_applies_only_without_file_or_flag_listeners() {
        let default = Some("tcp/0.0.0.0:7447");
        let alone = config_tree(&BusArgs::default(), None, default);
        assert_eq!(alone["listen"]["endpoints"], json!(["tcp/0.0.0.0:7447"]));
        let from_file = config_tree(&BusArgs::default(), Some(file()), default);
        assert_eq!(
            from_file["listen"]["endpoints"],
            json!(["tls/0.0.0.0:7448"])
        );
        let flag = BusArgs {
            listen: vec!["tcp/127.0.0.1:9001".into()],
            ..BusArgs::default()
        };
        let from_flag = config_tree(&flag, Some(file()), default);
        assert_eq!(
            from_flag["listen"]["endpoints"],
            json!(["tcp/127.0.0.1:9001"])
        );
    }

    #[test]
    fn router_config_reads_the_file_and_zenoh_accepts_the_merge() {
        let dir = std::env::temp_dir().join(format!("gh-bus-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("router.json5");
        std::fs::write(
            &path,
            r#"{ listen: { endpoints: ["tcp/127.0.0.1:7999"] }, transport: { link: { rx: { max_message_size: 1048576 } } } }"#,
        )
        .expect("write");
        let args = BusArgs {
            zenoh_config: Some(path),
            ..BusArgs::default()
        };
        let config = router_config(&args, "tcp/0.0.0.0:7447").expect("valid config");
        let listen = config.get_json("listen/endpoints").expect("listen");
        assert!(listen.contains("tcp/127.0.0.1:7999"), "{listen}");
        assert!(!listen.contains("7447"), "{listen}");
        assert_eq!(config.get_json("mode").expect("mode"), "\"router\"");
        assert_eq!(
            config
                .get_json("transport/link/rx/max_message_size")
                .expect("size"),
            "1048576"
        );
        assert_eq!(
            config
                .get_json("scouting/multicast/enabled")
                .expect("multicast"),
            "false"
        );
        let bad = dir.join("bad.json5");
        std::fs::write(&bad, "{ mode: \"nonsense\" }").expect("write");
        let args = BusArgs {
            zenoh_config: Some(bad),
            ..BusArgs::default()
        };
        let err = zenoh_config(&args).expect_err("an unknown mode is refused");
        assert!(err.to_string().contains("bad.json5"), "{err}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
