//! Pause instead of fail: faults that pass (an alarm mid-move, a camera stalling once, a
//! serial port that disappears and comes back, light that dips, garbled status reports)
//! each end in a complete session, `events.jsonl` tells what happened, and every planned
//! pair holds exactly one frame per role, taken where the plan says.

use lensrig::rig::config::{self, ControllerKind, RigConfig};
use lensrig::rig::controller::sim::{spawn_pty, SimObserver, SimOptions};
use lensrig::rig::events::{read_events, Event};
use lensrig::rig::session::{self, CaptureOptions, Rig};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

fn setup(name: &str) -> (RigConfig, PathBuf, PathBuf) {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("rig-configs/mock.toml");
    let mut cfg = config::load(&p).unwrap();
    cfg.camera.width = 96;
    cfg.camera.height = 72;
    cfg.camera.frames_to_average = 2;
    cfg.camera.frame_timeout_ms = 300;
    cfg.controller.timeouts.response_ms = 400;
    cfg.retry.pause_ms = 100;
    let out = std::env::temp_dir().join(format!("lensrig-pause-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    (cfg, p, out)
}

fn capture(rig: &mut Rig, cfg: &RigConfig, p: &Path, out: &Path) -> session::SessionRecord {
    session::capture(rig, cfg, p, out, &CaptureOptions { resume: false, progress: false }).unwrap()
}

/// Complete, every pair once with exactly its files, frames where the plan says, no frame
/// recorded twice; returns the event log.
fn check_complete(out: &Path, cfg: &RigConfig) -> Vec<Event> {
    let rec = session::load_session(out).unwrap();
    assert_eq!(rec.status, "complete");
    let plan = session::plan(cfg);
    assert_eq!(rec.pairs.iter().map(|r| r.key.clone()).collect::<Vec<_>>(), plan.iter().map(|p| p.key.clone()).collect::<Vec<_>>());
    let mut entries: Vec<String> = std::fs::read_dir(out.join("pairs")).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    entries.sort();
    assert_eq!(entries, plan.iter().map(|p| p.key.clone()).collect::<Vec<_>>(), "no partial or extra pair directories");
    let mut sequences = Vec::new();
    for p in &plan {
        let dir = out.join("pairs").join(&p.key);
        let mut files: Vec<String> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
        files.sort();
        assert_eq!(files, ["dark.png", "dark.toml", "open.png", "open.toml", "pinhole.png", "pinhole.toml"], "{}", p.key);
        for (role, aperture) in [("open", cfg.axes.aperture.open), ("pinhole", cfg.axes.aperture.pinhole), ("dark", cfg.axes.aperture.pinhole)] {
            let m = session::load_frame_record(&dir.join(format!("{role}.toml"))).unwrap();
            assert_eq!((m.stage_mm, m.aperture_mm), (p.stage_mm, aperture), "{} {role}", p.key);
            sequences.push(m.sequence.unwrap());
            let img = lensrig::image::io::read_image(&dir.join(format!("{role}.png"))).unwrap();
            assert_eq!((img.width(), img.height()), (cfg.camera.width as usize, cfg.camera.height as usize));
        }
    }
    let n = sequences.len();
    sequences.sort_unstable();
    sequences.dedup();
    assert_eq!(sequences.len(), n, "a frame was recorded twice");
    let ev = read_events(&out.join("events.jsonl")).unwrap();
    assert_eq!(ev.first().map(|e| e.kind.as_str()), Some("session-start"));
    assert_eq!(ev.last().map(|e| (e.kind.as_str(), e.detail.as_str())), Some(("session-end", "complete")));
    ev
}

fn kinds(ev: &[Event]) -> Vec<&str> {
    ev.iter().map(|e| e.kind.as_str()).filter(|k| !k.starts_with("session-")).collect()
}

fn has_line(board: &SimObserver, line: &str) -> bool {
    board.state().received_lines.iter().any(|l| l == line)
}

/// Calls `act` on another thread once the board has received `line`.
fn watch(rig: &Rig, line: &'static str, act: impl FnOnce(&SimObserver) + Send + 'static) -> std::thread::JoinHandle<()> {
    let board = rig.sim.as_ref().unwrap().observer();
    std::thread::spawn(move || {
        let t0 = Instant::now();
        while !has_line(&board, line) && t0.elapsed() < Duration::from_secs(30) {
            std::thread::sleep(Duration::from_millis(2));
        }
        act(&board);
    })
}

#[test]
fn an_alarm_in_the_middle_of_a_move_resets_rehomes_and_continues() {
    let (cfg, p, out) = setup("alarm");
    let mut rig = Rig::from_config(&cfg, None).unwrap();
    let w = watch(&rig, "G53G0X-40.000", |b| b.faults.hard_limit_on_move.store(true, Ordering::SeqCst));
    capture(&mut rig, &cfg, &p, &out);
    w.join().unwrap();
    let ev = check_complete(&out, &cfg);
    let k = kinds(&ev);
    assert_eq!(&k[..5], ["pause", "reset", "rehome", "retry", "recovered"], "{ev:?}");
    assert!(ev.iter().any(|e| e.kind == "pause" && e.detail.contains("001-stage-X-40.000: alarm: ") && e.detail.contains("ALARM:1")), "{ev:?}");
    let st = rig.sim.as_ref().unwrap().state();
    assert_eq!(st.received_lines.iter().filter(|l| *l == "$H").count(), 2, "homed on start and after the alarm");
    drop(st);
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn a_camera_that_stalls_longer_than_its_timeout_once_is_waited_for() {
    let (cfg, p, out) = setup("stall");
    let mut rig = Rig::from_config(&cfg, None).unwrap();
    let faults = rig.camera_faults.clone().unwrap();
    let w = watch(&rig, "G53G0Z-8.000", move |_| faults.stall_once_ms.store(1000, Ordering::SeqCst));
    capture(&mut rig, &cfg, &p, &out);
    w.join().unwrap();
    let ev = check_complete(&out, &cfg);
    assert_eq!(kinds(&ev), ["pause", "retry", "recovered"], "{ev:?}");
    assert!(ev[1].detail.contains("000-stage-X-20.000: camera-timeout: camera mock: no frame within 300ms"), "{ev:?}");
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn light_that_dips_pauses_the_pair_and_a_lasting_change_gives_up() {
    let (cfg, p, out) = setup("drift");
    let mut rig = Rig::from_config(&cfg, None).unwrap();
    let faults = rig.camera_faults.clone().unwrap();
    // the second pair's open frame (bracketing frame + open frame) sees 70 % of the light
    let w = watch(&rig, "G53G0X-40.000", move |_| faults.dim_captures.store(2, Ordering::SeqCst));
    capture(&mut rig, &cfg, &p, &out);
    w.join().unwrap();
    let ev = check_complete(&out, &cfg);
    assert_eq!(kinds(&ev), ["pause", "retry", "recovered"], "{ev:?}");
    assert!(ev[1].detail.contains("001-stage-X-40.000: drift: "), "{ev:?}");
    let change: f64 = ev[1].detail.split("open frame's light is ").nth(1).and_then(|t| t.split(' ').next()).unwrap().parse().unwrap();
    assert!((-33.0..-27.0).contains(&change), "the dip is 30 %: {change}");
    let _ = std::fs::remove_dir_all(&out);
    // without a dip the same session has no pause (the oracle: stage positions alone do not
    // trip the check)
    let mut rig = Rig::from_config(&cfg, None).unwrap();
    capture(&mut rig, &cfg, &p, &out);
    assert!(kinds(&check_complete(&out, &cfg)).is_empty());
    let _ = std::fs::remove_dir_all(&out);
    // light that stays low: the pair gives up after max_tries, naming the drift
    let mut rig = Rig::from_config(&cfg, None).unwrap();
    let faults = rig.camera_faults.clone().unwrap();
    let w = watch(&rig, "G53G0X-40.000", move |_| faults.dim_captures.store(1000, Ordering::SeqCst));
    let e = session::capture(&mut rig, &cfg, &p, &out, &CaptureOptions { resume: false, progress: false }).unwrap_err().to_string();
    w.join().unwrap();
    assert!(e.contains("illumination drift") && e.contains("gave up after 3 tries"), "{e}");
    let ev = read_events(&out.join("events.jsonl")).unwrap();
    assert_eq!(ev.iter().filter(|e| e.kind == "pause").count(), 2);
    assert!(ev.iter().any(|e| e.kind == "gave-up"));
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn garbled_status_reports_at_1_and_10_percent_are_counted_noise() {
    for (ppm, name) in [(10_000u32, "noise1"), (100_000, "noise10")] {
        let (cfg, p, out) = setup(name);
        let mut rig = Rig::from_config(&cfg, None).unwrap();
        rig.sim.as_ref().unwrap().faults.corrupt_reports_ppm.store(ppm, Ordering::SeqCst);
        capture(&mut rig, &cfg, &p, &out);
        let ev = check_complete(&out, &cfg);
        let st = rig.sim.as_ref().unwrap().state();
        let corrupt = ev.iter().filter(|e| e.kind == "corrupt-line").count();
        eprintln!("{}: {} of {} reports corrupted, {corrupt} corrupt lines logged, events {:?}", name, st.reports_corrupted, st.status_reports_sent, kinds(&ev));
        // the first report drawn is corrupted (the sim's seed); run-on lines can merge two
        assert!(st.reports_corrupted >= 1 && corrupt >= 1 && corrupt <= st.reports_corrupted, "{corrupt} vs {}", st.reports_corrupted);
        assert!(!kinds(&ev).contains(&"pause"), "noise alone never pauses a pair: {ev:?}");
        drop(st);
        let _ = std::fs::remove_dir_all(&out);
    }
}

#[cfg(unix)]
#[test]
fn a_serial_port_that_disappears_and_comes_back_is_reopened_and_rehomed() {
    // a by-id style symlink, as udev makes: the board re-enumerates on another pty
    let (mut cfg, p, out) = setup("unplug");
    let dir = std::env::temp_dir().join(format!("lensrig-pause-{}-unplug-dev", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let link = dir.join("usb-grbl-if00-port0");
    let (board1, path1) = spawn_pty(SimOptions::fast().with(22, 1.0)).unwrap();
    std::os::unix::fs::symlink(&path1, &link).unwrap();
    cfg.controller.kind = ControllerKind::Serial;
    cfg.controller.port = Some(link.display().to_string());
    cfg.retry.max_tries = 6;
    let mut rig = Rig::from_config(&cfg, None).unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let relink = link.clone();
    let w = std::thread::spawn(move || {
        let t0 = Instant::now();
        while !has_line(&board1.observer(), "G53G0X-40.000") && t0.elapsed() < Duration::from_secs(30) {
            std::thread::sleep(Duration::from_millis(2));
        }
        board1.faults.disconnect.store(true, Ordering::SeqCst); // cable pulled mid-pair
        std::thread::sleep(Duration::from_millis(300));
        let (board2, path2) = spawn_pty(SimOptions::fast().with(22, 1.0)).unwrap();
        let tmp = relink.with_extension("new");
        std::os::unix::fs::symlink(&path2, &tmp).unwrap();
        std::fs::rename(&tmp, &relink).unwrap();
        tx.send(board2).unwrap();
        board1
    });
    capture(&mut rig, &cfg, &p, &out);
    let _board1 = w.join().unwrap();
    let board2 = rx.recv().unwrap();
    let ev = check_complete(&out, &cfg);
    let k = kinds(&ev);
    assert!(k.first() == Some(&"pause") && ev.iter().any(|e| e.kind == "pause" && e.detail.contains("disconnect: ")), "{ev:?}");
    assert!(ev.iter().any(|e| e.kind == "reconnect" && e.detail.contains("usb-grbl-if00-port0") && e.detail.contains("homed")), "{ev:?}");
    assert_eq!(k.last(), Some(&"recovered"));
    // the new board was homed, then did the rest of the plan
    let st = board2.state();
    assert!(st.homed && st.received_lines.iter().any(|l| l == "G53G0X-60.000"), "{:?}", st.received_lines);
    drop(st);
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(&dir);
}
