//! An X display for the tests that open a window (shared by the test binaries that include it).

use std::path::{Path, PathBuf};
use std::process::Command;

/// An X display for window tests: `$DISPLAY` if set, else an Xvfb started for the test (stopped
/// on drop). `None` — the test skips — where there is neither and the environment does not
/// require one (CI installs Xvfb and sets `VLF_REQUIRE_GPU`).
pub struct XDisplay {
    pub name: String,
    server: Option<std::process::Child>,
}

impl Drop for XDisplay {
    fn drop(&mut self) {
        if let Some(server) = &mut self.server {
            // SIGTERM lets Xvfb remove its socket and lock file.
            let _ = Command::new("kill").args(["-TERM", &server.id().to_string()]).status();
            let _ = server.wait();
        }
    }
}

pub fn x_display() -> Option<XDisplay> {
    if let Ok(name) = std::env::var("DISPLAY")
        && !name.is_empty()
    {
        return Some(XDisplay { name, server: None });
    }
    // One server per call: tests of one binary run in parallel, each stopping its own.
    static CALLS: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let call = CALLS.fetch_add(1, std::sync::atomic::Ordering::Relaxed) % 10;
    let number = 100 + (std::process::id() % 90) * 10 + call;
    let socket = PathBuf::from(format!("/tmp/.X11-unix/X{number}"));
    if socket.exists() && !Path::new(&format!("/tmp/.X{number}-lock")).exists() {
        // Left by a server that was killed: it would pass for this one being up.
        let _ = std::fs::remove_file(&socket);
    }
    let server = Command::new("Xvfb")
        .args([&format!(":{number}"), "-screen", "0", "640x480x24", "-nolisten", "tcp"])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn();
    let server = match server {
        Ok(s) => s,
        Err(e) => {
            assert!(
                std::env::var_os("VLF_REQUIRE_GPU").is_none(),
                "VLF_REQUIRE_GPU is set but Xvfb cannot start: {e}"
            );
            eprintln!("skipped: no DISPLAY and no Xvfb ({e})");
            return None;
        }
    };
    let display = XDisplay {
        name: format!(":{number}"),
        server: Some(server),
    };
    for _ in 0..100 {
        if socket.exists() {
            return Some(display);
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    panic!("Xvfb {} did not come up", display.name);
}
