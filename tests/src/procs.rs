//! The real binaries as OS processes: build them, start them with a log file each, stop them.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// target/<profile>/ of this test binary (it lives in target/<profile>/deps/).
pub fn bin_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test binary path");
    exe.parent()
        .and_then(Path::parent)
        .expect("target/<profile>/deps")
        .to_path_buf()
}

/// Builds the service binaries (a no-op when cargo already has), so `cargo test` alone works.
pub fn build_binaries() {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let release = bin_dir().ends_with("release");
    let mut cmd = Command::new(cargo);
    // The test harness sets per-crate variables (CARGO_PKG_*, CARGO_MANIFEST_DIR, ...) that build
    // scripts watch; passing them on would make this build redo work the outer one already did.
    for (name, _) in std::env::vars_os() {
        let name = name.to_string_lossy().into_owned();
        let keep = [
            "CARGO_HOME",
            "CARGO_TARGET_DIR",
            "CARGO_TERM_COLOR",
            "CARGO_INCREMENTAL",
        ]
        .contains(&name.as_str())
            || name.starts_with("CARGO_BUILD_")
            || name.starts_with("CARGO_PROFILE_");
        if !keep && (name.starts_with("CARGO_") || name.starts_with("NEXTEST") || name == "OUT_DIR")
        {
            cmd.env_remove(&name);
        }
    }
    // The same selection as scripts/test builds, so this is a no-op there.
    cmd.args(["build", "--workspace", "--bins"]);
    if release {
        cmd.arg("--release");
    }
    let status = cmd.status().expect("cargo runs");
    assert!(status.success(), "building the service binaries failed");
}

pub struct Proc {
    pub name: &'static str,
    pub child: Child,
    pub log: PathBuf,
}

impl Proc {
    pub fn start(name: &'static str, bin: &str, args: &[&str], logs: &Path) -> Proc {
        let log = logs.join(format!("{name}.log"));
        let file = std::fs::File::create(&log).expect("log file");
        let child = Command::new(bin_dir().join(bin))
            .args(args)
            .env("RUST_LOG", "info")
            .stdout(Stdio::null())
            .stderr(file)
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {bin}: {e}"));
        Proc { name, child, log }
    }

    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// SIGTERM, then the process must exit successfully on its own.
    pub fn terminate(mut self) {
        let pid = self.child.id().to_string();
        let _ = Command::new("kill").args(["-TERM", &pid]).status();
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            match self.child.try_wait().expect("wait") {
                Some(status) => {
                    assert!(
                        status.success(),
                        "{} exited with {status}:\n{}",
                        self.name,
                        self.log_text()
                    );
                    return;
                }
                None if Instant::now() > deadline => {
                    let _ = self.child.kill();
                    panic!("{} ignored SIGTERM:\n{}", self.name, self.log_text());
                }
                None => std::thread::sleep(Duration::from_millis(50)),
            }
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        // A failing test shows what each of its processes said last (CI keeps no log files).
        if std::thread::panicking() {
            let text = self.log_text();
            let lines: Vec<&str> = text.lines().collect();
            let tail = &lines[lines.len().saturating_sub(LOG_TAIL_LINES)..];
            eprintln!(
                "--- the last {} lines of {} ({}):\n{}",
                tail.len(),
                self.name,
                self.log.display(),
                tail.join("\n")
            );
        }
    }
}

/// How much of a process's log a failing test prints.
const LOG_TAIL_LINES: usize = 40;

impl Proc {
    /// SIGKILL: the process gets no chance to say goodbye (a crashed or killed service).
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Proc {
    /// SIGSTOP: the process hangs (a stuck planner, a host that stops answering) with its links
    /// left open; peers notice only when their lease expires.
    pub fn pause(&self) {
        self.signal("-STOP");
    }

    /// SIGCONT: a paused process runs on from where it stopped, unaware of the time it lost.
    pub fn resume(&self) {
        self.signal("-CONT");
    }

    /// A relay (`glasshouse relay`) cuts its link (SIGUSR1): no byte passes, nothing closes, as
    /// behind a dead switch; peers notice only when their lease expires.
    pub fn cut(&self) {
        self.signal("-USR1");
    }

    /// A relay heals its link (SIGUSR2).
    pub fn heal(&self) {
        self.signal("-USR2");
    }

    fn signal(&self, signal: &str) {
        let pid = self.child.id().to_string();
        let status = Command::new("kill").args([signal, &pid]).status();
        assert!(
            status.is_ok_and(|s| s.success()),
            "kill {signal} {} failed",
            self.name
        );
    }
}
