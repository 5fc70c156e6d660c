//! Faults on the simulated rig that outlast `retry.max_tries` (library level, so they can be
//! injected mid-session): each gives a clear error, the session says `failed: …`, and no
//! finished pair is half-written. Faults that pass are in `rig_pause.rs`.

mod common;

use lensrig::rig::config::{self, RigConfig};
use lensrig::rig::session::{self, CaptureOptions, Rig};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;

fn setup(name: &str) -> (RigConfig, PathBuf, PathBuf) {
    let p = common::mock();
    let mut cfg = config::load(&p).unwrap();
    cfg.camera.width = 128;
    cfg.camera.height = 96;
    cfg.camera.frames_to_average = 1;
    cfg.controller.timeouts.response_ms = 400;
    let out = common::tmp("faults", name);
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
    // (a one-shot alarm is recovered from: tests/rig_pause.rs)
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

/// The 99.9th percentile and the clipped fraction of a recorded frame.
fn clip_stats(path: &Path) -> (f32, f64) {
    let img = lensrig::image::io::read_image(path).unwrap();
    let mut v: Vec<f32> = img.planes[0].data.clone();
    v.sort_by(f32::total_cmp);
    let clipped = v.iter().filter(|&&x| x >= 0.9999).count() as f64 / v.len() as f64;
    (v[(v.len() - 1) * 999 / 1000], clipped)
}

#[test]
fn auto_bracketing_keeps_the_open_frame_below_clipping_and_scales_the_pinhole() {
    let (mut cfg, p, out) = setup("bracket");
    cfg.axes.stage.positions.truncate(1);
    cfg.camera.exposure_us = 640_000; // 8× too long for the mock's light: the open frame clips
    // without bracketing it really clips (the oracle for the check below)
    cfg.plan.auto_bracket = false;
    let mut rig = Rig::from_config(&cfg, None).unwrap();
    session::capture(&mut rig, &cfg, &p, &out, &CaptureOptions { resume: false, progress: false }).unwrap();
    let pair = out.join("pairs/000-stage-X-20.000");
    let (_, clipped) = clip_stats(&pair.join("open.png"));
    assert!(clipped > 0.01, "{clipped}");
    let _ = std::fs::remove_dir_all(&out);
    cfg.plan.auto_bracket = true;
    let mut rig = Rig::from_config(&cfg, None).unwrap();
    session::capture(&mut rig, &cfg, &p, &out, &CaptureOptions { resume: false, progress: false }).unwrap();
    let (p999, _) = clip_stats(&pair.join("open.png"));
    assert!(p999 < 0.95, "{p999}");
    let open = session::load_frame_record(&pair.join("open.toml")).unwrap();
    let pin = session::load_frame_record(&pair.join("pinhole.toml")).unwrap();
    let dark = session::load_frame_record(&pair.join("dark.toml")).unwrap();
    assert!(open.exposure_us < 640_000 && open.exposure_us > 20_000, "{}", open.exposure_us);
    assert_eq!(pin.exposure_us as f64, (open.exposure_us as f64 * cfg.plan.pinhole_exposure_scale).round());
    assert_eq!((dark.exposure_us, dark.frames_averaged), (1, cfg.plan.dark_frames as usize));
    // the frames were taken where the controller said the aperture was
    assert_eq!((open.aperture_mm, pin.aperture_mm, open.stage_mm), (cfg.axes.aperture.open, cfg.axes.aperture.pinhole, -20.0));
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn light_too_bright_to_bracket_stops_instead_of_recording_a_clipped_frame() {
    let (mut cfg, p, out) = setup("saturated");
    cfg.lens.as_mut().unwrap().insert("brightness".into(), toml::Value::Float(1e8));
    let mut rig = Rig::from_config(&cfg, None).unwrap();
    let e = session::capture(&mut rig, &cfg, &p, &out, &CaptureOptions { resume: false, progress: false }).unwrap_err().to_string();
    assert!(e.contains("000-stage-X-20.000: the open frame still clips") && e.contains("reduce the light"), "{e}");
    check_integrity(&out, "still clips");
    // nothing was recorded for the pair
    assert!(!out.join("pairs/000-stage-X-20.000").exists());
    let _ = std::fs::remove_dir_all(&out);
}
