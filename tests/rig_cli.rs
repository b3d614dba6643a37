//! The `subsurf` binary's rig commands: `rig --sim`, and a scripted session against
//! `rig serve-sim` over its pseudo-terminal.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Output, Stdio};

const BIN: &str = env!("CARGO_BIN_EXE_subsurf");

fn subsurf<S: AsRef<std::ffi::OsStr> + std::fmt::Debug>(args: &[S]) -> Output {
    Command::new(BIN).args(args).output().expect("run subsurf")
}

fn stdout_of<S: AsRef<std::ffi::OsStr> + std::fmt::Debug>(args: &[S]) -> String {
    let out = subsurf(args);
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "subsurf {args:?} failed: {}\n{stdout}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

#[test]
fn rig_sim_hello() {
    let out = stdout_of(&["rig", "--sim", "hello"]);
    let version = format!("protocol version: {}", subsurf_protocol::PROTOCOL_VERSION);
    assert!(out.contains(&version), "{out}");
    assert!(out.contains("steps per revolution:"), "{out}");
}

#[test]
fn rig_sim_move_and_capture() {
    let out = stdout_of(&["rig", "--sim", "move", "--by", "-250"]);
    assert!(out.contains("position: -250"), "{out}");
    let out = stdout_of(&["rig", "--sim", "capture", "--x", "7", "--y", "9"]);
    assert!(
        out.contains("capture 0:") && out.contains("galvo 7 9"),
        "{out}"
    );
}

#[test]
fn rig_sim_selftest_passes_every_step_it_can_check() {
    let out = stdout_of(&["rig", "--sim", "selftest", "--yes"]);
    for step in [
        "PASS handshake",
        "PASS profile read-back",
        "PASS config read-back",
        "PASS home:",
        "PASS home twice and compare: second zero 0 steps",
        "PASS step count by the home switch",
        "PASS profile stored",
        "PASS trigger and exposure-active loopback",
        "PASS galvo sweep",
        "SKIP interlock",
        "SKIP e-stop",
    ] {
        assert!(out.contains(step), "{step:?} missing:\n{out}");
    }
    assert!(out.contains(" 0 failed"), "{out}");
}

#[test]
fn rig_profile_default_check_and_sim_run_the_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("rig.json");
    let json = stdout_of(&["rig", "profile", "default", "--internal-dac"]);
    std::fs::write(&file, &json).expect("write");
    let f = file.to_str().expect("utf-8 path");
    let check = stdout_of(&["rig", "--profile", f, "profile", "check"]);
    assert!(check.contains("codes 0..=4095"), "{check}");
    let hello = stdout_of(&["rig", "--sim", "--profile", f, "hello"]);
    assert!(hello.contains("galvo codes: 0..=4095"), "{hello}");
    // A bad file is a clear error naming the field group.
    std::fs::write(
        &file,
        json.replace("\"microsteps\": 16", "\"microsteps\": 0"),
    )
    .expect("write");
    let out = subsurf(&["rig", "--profile", f, "profile", "check"]);
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("Gearing"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn missing_port_and_missing_choice_are_clear_errors() {
    let out = subsurf(&["rig", "--port", "/dev/no-such-rig", "status"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("/dev/no-such-rig"), "{err}");
    let out = subsurf(&["rig", "status"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--sim"));
}

/// Kills the server even when an assertion fails.
struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn scripted_session_against_serve_sim() {
    let mut server = Server(
        Command::new(BIN)
            .args(["rig", "serve-sim"])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("start serve-sim"),
    );
    let stdout = server.0.stdout.take().expect("stdout");
    let mut first = String::new();
    BufReader::new(stdout)
        .read_line(&mut first)
        .expect("first line");
    let path = first.trim().to_owned();
    assert!(
        path.starts_with("/dev/"),
        "first line is the pty path: {first:?}"
    );

    let with = |rest: &[&'static str]| -> Vec<String> {
        ["rig", "--port", path.as_str()]
            .iter()
            .chain(rest)
            .map(|s| s.to_string())
            .collect()
    };
    let hello = stdout_of(&with(&["hello"]));
    assert!(hello.contains("protocol version:"), "{hello}");
    let homed = stdout_of(&with(&["home"]));
    assert!(homed.contains("homed: true"), "{homed}");
    let moved = stdout_of(&with(&["move", "--to", "400"]));
    assert!(moved.contains("position: 400"), "{moved}");
    let moved = stdout_of(&with(&["move", "--by", "-100"]));
    assert!(moved.contains("position: 300"), "{moved}");
    stdout_of(&with(&["galvo", "1000", "2000"]));
    let capture = stdout_of(&with(&[
        "capture",
        "--x",
        "11",
        "--y",
        "12",
        "--exposure-us",
        "2000",
    ]));
    assert!(capture.contains("galvo 11 12"), "{capture}");
    let status = stdout_of(&with(&["status"]));
    assert!(status.contains("position: 300"), "{status}");
    assert!(status.contains("armed: false"), "{status}");
    assert!(status.contains("next capture id: 1"), "{status}");
    let stop = stdout_of(&with(&["stop"]));
    assert!(stop.contains("stopped"), "{stop}");
}
