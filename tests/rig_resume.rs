//! Interrupted captures through the real binary on the simulated rig: a SIGKILL between and
//! inside pairs, a kill between a pair's rename and the session update, a damaged finished
//! pair, and a disk that fills. After each, `--resume` finishes the session without touching
//! the pairs that were already finished, and nothing half-written is left or trusted.

mod common;

use common::bin;
use lensrig::rig::session;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

fn tmp(name: &str) -> PathBuf {
    common::tmp("resume", name)
}

/// A copy of mock.toml (absolute target path, small frames) with `edit` applied.
fn config_variant(dir: &Path, edit: impl Fn(String) -> String) -> PathBuf {
    common::mock_config(dir, |text| {
        edit(text.replace("frames_to_average = 16", "frames_to_average = 2").replace("width = 384", "width = 192").replace("height = 288", "height = 144"))
    })
}

fn capture(cfg: &Path, s: &Path, resume: bool) -> Output {
    let mut c = bin();
    c.args(["capture", "--rig", cfg.to_str().unwrap(), "--out", s.to_str().unwrap(), "--quiet"]);
    if resume {
        c.arg("--resume");
    }
    c.output().unwrap()
}

fn ok(o: Output) -> String {
    common::succeeded(o)
}

const FILES: [&str; 6] = ["open.png", "open.toml", "pinhole.png", "pinhole.toml", "dark.png", "dark.toml"];

fn snapshot(pair: &Path) -> Vec<Vec<u8>> {
    FILES.iter().map(|f| std::fs::read(pair.join(f)).unwrap_or_else(|e| panic!("{}: {e}", pair.join(f).display()))).collect()
}

/// Every file under `dir`, recursively.
fn all_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.push(p.clone());
            out.extend(all_files(&p));
        } else {
            out.push(p);
        }
    }
    out
}

/// A complete session: every planned pair finished and verified, recorded in order, nothing
/// unfinished or temporary anywhere.
fn assert_complete(s: &Path, keys: &[&str]) {
    let rec = session::load_session(s).unwrap();
    assert_eq!(rec.status, "complete");
    assert_eq!(rec.pairs.iter().map(|p| p.key.as_str()).collect::<Vec<_>>(), keys);
    assert_eq!(rec.pairs.iter().map(|p| p.index).collect::<Vec<_>>(), (0..keys.len()).collect::<Vec<_>>());
    for k in keys {
        let d = s.join("pairs").join(k);
        for f in FILES {
            assert!(d.join(f).is_file(), "{} lacks {f}", d.display());
        }
        lensrig::image::io::read_image(&d.join("open.png")).unwrap();
        lensrig::image::io::read_image(&d.join("pinhole.png")).unwrap();
    }
    for p in all_files(s) {
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        assert!(!name.contains(".tmp-") && !name.ends_with(".partial"), "left behind: {}", p.display());
    }
}

/// Polls (every 2 ms) until `cond` holds, the child exits, or 120 s pass.
fn wait_for(child: &mut std::process::Child, what: &str, cond: impl Fn() -> bool) {
    let t = Instant::now();
    while !cond() {
        if let Some(st) = child.try_wait().unwrap() {
            panic!("capture exited ({st}) before {what}");
        }
        assert!(t.elapsed() < Duration::from_secs(120), "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(2));
    }
}

#[test]
fn sigkill_inside_the_second_pair_then_resume_keeps_the_first_byte_identical() {
    let dir = tmp("kill");
    // settle 400 ms before each frame: the first pair's rename and the second pair's open
    // frame leave ≥ 400 ms before the second pair could finish, ample time to kill it
    let cfg = config_variant(&dir, |t| t.replace("settle_ms = 0", "settle_ms = 400").replace("positions = [-20.0, -40.0, -60.0]", "positions = [-20.0, -40.0, -60.0, -80.0]"));
    let s = dir.join("session");
    let mut child = bin()
        .args(["capture", "--rig", cfg.to_str().unwrap(), "--out", s.to_str().unwrap(), "--quiet"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let first = s.join("pairs/000-stage-X-20.000");
    let second_open = s.join("pairs/001-stage-X-40.000.partial/open.toml");
    wait_for(&mut child, "the second pair's open frame", || second_open.is_file());
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    // killed: the first pair finished, the second one unfinished, the session says running
    assert!(first.is_dir() && !s.join("pairs/001-stage-X-40.000").exists());
    let rec = session::load_session(&s).unwrap();
    assert_eq!(rec.status, "running");
    assert_eq!(rec.pairs.len(), 1);
    let before = snapshot(&first);
    // what a kill in the middle of an atomic write leaves: its temporary files (a half-written
    // frame never has a frame's name)
    std::fs::write(s.join("pairs/001-stage-X-40.000.partial/.pinhole.png.tmp-99999"), b"\x89PNG half").unwrap();
    std::fs::write(s.join(".session.toml.tmp-99999"), b"status = \"runn").unwrap();
    ok(capture(&cfg, &s, true));
    assert_complete(&s, &["000-stage-X-20.000", "001-stage-X-40.000", "002-stage-X-60.000", "003-stage-X-80.000"]);
    assert!(before == snapshot(&first), "a finished pair changed on resume");
    let rec = session::load_session(&s).unwrap();
    assert_eq!(rec.resumed.len(), 1);
    assert!(rec.finished.is_some());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn resume_records_an_unrecorded_pair_and_recaptures_a_damaged_one() {
    let dir = tmp("recover");
    let cfg = config_variant(&dir, |t| t.replace("positions = [-20.0, -40.0, -60.0]", "positions = [-20.0, -40.0]"));
    let s = dir.join("session");
    ok(capture(&cfg, &s, false));
    let keys = ["000-stage-X-20.000", "001-stage-X-40.000"];
    assert_complete(&s, &keys);
    // as if killed between the second pair's rename and the session update ...
    let mut rec = session::load_session(&s).unwrap();
    rec.pairs.truncate(1);
    rec.status = "running".into();
    rec.finished = None;
    std::fs::write(s.join("session.toml"), toml::to_string(&rec).unwrap()).unwrap();
    let second = snapshot(&s.join("pairs").join(keys[1]));
    // ... and with the first pair's pinhole frame cut short on disk (not something lensrig
    // writes; a resume must still not trust it)
    let pin = s.join("pairs").join(keys[0]).join("pinhole.png");
    let bytes = std::fs::read(&pin).unwrap();
    std::fs::write(&pin, &bytes[..bytes.len() / 2]).unwrap();
    let o = bin().args(["capture", "--rig", cfg.to_str().unwrap(), "--out", s.to_str().unwrap(), "--resume"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("000-stage-X-20.000 is damaged") && err.contains("001-stage-X-40.000 finished but was not yet recorded"), "{err}");
    assert_complete(&s, &keys);
    assert!(second == snapshot(&s.join("pairs").join(keys[1])), "the unrecorded pair was recaptured");
    // the damaged pair is kept aside, not deleted, and was captured again
    assert_eq!(std::fs::read(s.join("pairs/000-stage-X-20.000.damaged/pinhole.png")).unwrap(), &bytes[..bytes.len() / 2]);
    lensrig::image::io::read_image(&pin).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_full_disk_fails_clearly_keeps_finished_pairs_and_resume_finishes() {
    let dir = tmp("full");
    let cfg = config_variant(&dir, |t| t);
    let s = dir.join("session");
    // first run: the camera stops after the first pair (4 captures per pair)
    let o = bin().args(["capture", "--rig", cfg.to_str().unwrap(), "--out", s.to_str().unwrap(), "--quiet"]).env("LENSRIG_MOCK_TIMEOUT_AFTER_CAPTURES", "6").output().unwrap();
    assert!(!o.status.success());
    let first = s.join("pairs/000-stage-X-20.000");
    let before = snapshot(&first);
    let biggest = FILES.iter().map(|f| before[FILES.iter().position(|g| g == f).unwrap()].len()).max().unwrap();
    let toml_size = std::fs::metadata(s.join("session.toml")).unwrap().len() as usize;
    // second run: no file may grow beyond 16 KiB (the kernel refuses the write with EFBIG,
    // as a full disk refuses it with ENOSPC): session.toml fits, a frame does not
    let limit_blocks = 32; // 512-byte blocks
    assert!(toml_size < limit_blocks * 512 / 2 && biggest > limit_blocks * 512, "frame {biggest} B, session.toml {toml_size} B");
    let o = Command::new("sh")
        .arg("-c")
        .arg(format!("trap '' XFSZ; ulimit -f {limit_blocks} && exec \"$0\" \"$@\""))
        .arg(env!("CARGO_BIN_EXE_lensrig"))
        .args(["capture", "--rig", cfg.to_str().unwrap(), "--out", s.to_str().unwrap(), "--quiet", "--resume"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(err.contains("no space to write the capture") && err.contains("001-stage-X-40.000.partial/open.png") && err.contains("--resume"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "one clear line: {err}");
    let rec = session::load_session(&s).unwrap();
    assert!(rec.status.starts_with("failed:") && rec.status.contains("no space"), "{}", rec.status);
    assert_eq!(rec.pairs.len(), 1);
    assert!(before == snapshot(&first), "a finished pair changed");
    // the refused frame left nothing behind: neither its name nor a temporary file
    let partial = s.join("pairs/001-stage-X-40.000.partial");
    assert_eq!(std::fs::read_dir(&partial).unwrap().count(), 0, "{:?}", all_files(&partial));
    // space again: resume finishes
    ok(capture(&cfg, &s, true));
    assert_complete(&s, &["000-stage-X-20.000", "001-stage-X-40.000", "002-stage-X-60.000"]);
    assert!(before == snapshot(&first));
    let _ = std::fs::remove_dir_all(&dir);
}
