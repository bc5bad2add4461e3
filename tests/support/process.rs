//! The `vlf` binary as the end-to-end tests run it (shared by the test binaries that include
//! it): processes that log to a file and are killed when dropped, so a failing test leaves
//! nothing running.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::Duration;

pub const VLF: &str = env!("CARGO_BIN_EXE_vlf");

/// The mirror scene's job parameters at a size that runs in a second: mirrors make specular
/// radiance cross workers, perturbation (on by default) makes iterations of several passes.
pub const PARAMS: [&str; 8] = [
    "--directions",
    "33",
    "--resolution",
    "16",
    "--tile",
    "4",
    "--encoding",
    "f32",
];

/// `vlf` without the caller's `VLF_TOKEN` and `VLF_SERVER`: a test says what it means.
pub fn vlf_command() -> Command {
    let mut command = Command::new(VLF);
    command.env_remove("VLF_TOKEN").env_remove("VLF_SERVER");
    command
}

/// A child process killed (SIGKILL) when dropped.
pub struct Proc {
    pub child: Child,
    pub name: String,
    pub log: PathBuf,
}

impl Proc {
    /// Starts `command` with its stdout piped and its stderr in `dir/NAME.log`.
    pub fn spawn(mut command: Command, dir: &Path, name: &str) -> Proc {
        let log = dir.join(format!("{name}.log"));
        let child = command
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&log).expect("log file"))
            .spawn()
            .expect("spawn vlf");
        Proc {
            child,
            name: name.to_string(),
            log,
        }
    }

    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// The first stdout line containing `needle` (the process must print it within a minute).
    pub fn wait_for_line(&mut self, needle: &str) -> String {
        let stdout = self.child.stdout.take().expect("stdout piped");
        let (tx, rx) = std::sync::mpsc::channel();
        let needle = needle.to_string();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if line.contains(&needle) {
                    let _ = tx.send(line);
                    return;
                }
            }
        });
        match rx.recv_timeout(Duration::from_secs(60)) {
            Ok(line) => line,
            Err(_) => panic!("{} never printed the line; its log:\n{}", self.name, self.log()),
        }
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A free loopback port (for a server that must come back on the same address, or whose
/// address a file names before it starts).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A finished command's exit status and output, for a failing assertion's message.
pub fn describe(o: &Output) -> String {
    format!(
        "status {:?}\nstdout:\n{}\nstderr:\n{}",
        o.status.code(),
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}
