//! Faults on the simulated rig (library level, so they can be injected mid-session): each
//! gives a clear error, the session says `failed: …`, and no finished pair is half-written.

use lensrig::rig::config::{self, RigConfig};
use lensrig::rig::session::{self, CaptureOptions, Rig};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;

fn setup(name: &str) -> (RigConfig, PathBuf, PathBuf) {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("rig-configs/mock.toml");
    let mut cfg = config::load(&p).unwrap();
    cfg.camera.width = 128;
    cfg.camera.height = 96;
    cfg.camera.frames_to_average = 1;
    cfg.controller.timeouts.response_ms = 400;
    let out = std::env::temp_dir().join(format!("lensrig-faults-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    (cfg, p, out)
}

/// Finished pairs are complete; the failed session names the error.
fn check_integrity(out: &Path, want: &str) {
    let rec = session::load_session(out).unwrap();
    assert!(rec.status.starts_with("failed:") && rec.status.contains(want), "{}", rec.status);
    for e in std::fs::read_dir(out.join("pairs")).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "partial") {
            continue;
        }
        for f in ["open.png", "open.toml", "pinhole.png", "pinhole.toml"] {
            assert!(p.join(f).is_file(), "{} lacks {f}", p.display());
        }
        lensrig::image::io::read_image(&p.join("open.png")).unwrap();
    }
    for r in &rec.pairs {
        assert!(out.join(&r.dir).is_dir());
    }
}

fn run_with(name: &str, inject: impl Fn(&Rig), want: &str) {
    let (cfg, p, out) = setup(name);
    let mut rig = Rig::from_config(&cfg, None).unwrap();
    inject(&rig);
    let e = session::capture(&mut rig, &cfg, &p, &out, &CaptureOptions { resume: false, progress: false }).unwrap_err().to_string();
    assert!(e.contains(want), "{name}: {e}");
    eprintln!("{name}: {e}");
    check_integrity(&out, want);
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn serial_faults_fail_clearly() {
    run_with("silent", |r| r.sim.as_ref().unwrap().faults.silent.store(true, Ordering::SeqCst), "within");
    run_with("garbage", |r| r.sim.as_ref().unwrap().faults.garbage.store(true, Ordering::SeqCst), "unreadable bytes");
    run_with("disconnect", |r| r.sim.as_ref().unwrap().faults.disconnect.store(true, Ordering::SeqCst), "");
    run_with("alarm", |r| r.sim.as_ref().unwrap().faults.hard_limit_on_move.store(true, Ordering::SeqCst), "ALARM");
}

#[test]
fn camera_faults_fail_clearly_or_recover() {
    run_with("camera-timeout", |r| r.camera_faults.as_ref().unwrap().timeout.store(true, Ordering::SeqCst), "no frame within");
    // dropped frames are replaced and counted; the session completes
    let (cfg, p, out) = setup("drop");
    let mut rig = Rig::from_config(&cfg, None).unwrap();
    rig.camera_faults.as_ref().unwrap().drop_frames.store(3, Ordering::SeqCst);
    let rec = session::capture(&mut rig, &cfg, &p, &out, &CaptureOptions { resume: false, progress: false }).unwrap();
    assert_eq!(rec.status, "complete");
    assert_eq!(rec.pairs.len(), 3);
    let _ = std::fs::remove_dir_all(&out);
}
