//! The rig end to end on the simulated hardware (grbl firmware on a pty + mock camera), through
//! the real binary: calibrate against the simulator's truth, dry runs, never-overwrite, resume.

mod common;

use common::{bin, fails, mock, ok};
use lensrig::estimate::relative_error;
use lensrig::profile::Profile;
use lensrig::rig::camera::mock::MockOptics;
use lensrig::rig::config;
use std::path::{Path, PathBuf};

fn tmp(name: &str) -> PathBuf {
    common::tmp("rig", name)
}

/// A copy of mock.toml with absolute target path and `edit` applied.
fn config_variant(dir: &Path, edit: impl Fn(String) -> String) -> PathBuf {
    common::mock_config(dir, edit)
}

#[test]
fn calibrate_on_the_mock_rig_recovers_the_true_psfs() {
    let out = tmp("calibrate");
    let rig = mock();
    let t = std::time::Instant::now();
    let stdout = ok(&["calibrate", "--rig", rig.to_str().unwrap(), "--out", out.to_str().unwrap(), "--quiet"]);
    eprintln!("{stdout} ({:.1} s)", t.elapsed().as_secs_f64());
    assert!(out.join("index.html").is_file() && out.join("summary.json").is_file());
    let session = std::fs::read_to_string(out.join("session/session.toml")).unwrap();
    assert!(session.contains("status = \"complete\""), "{session}");
    // truth, computed here with the same lens model and f-number the mock renders with
    let cfg = config::load(&rig).unwrap();
    let optics = MockOptics::from_config(&cfg).unwrap();
    let truth = optics.truth_grid(optics.f_number_open);
    let keys: Vec<_> = lensrig::rig::session::plan(&cfg).into_iter().map(|p| p.key).collect();
    assert_eq!(keys.len(), 3);
    for key in keys {
        let prof = Profile::load(&out.join("profiles").join(&key)).unwrap();
        let g = &prof.grid;
        let mut e: Vec<f64> = (0..g.tile_count()).map(|t| relative_error(&g.kernels[0][t], &truth.kernel_at(0, g.centers[t][0], g.centers[t][1]))).collect();
        e.sort_by(f64::total_cmp);
        let med = e[e.len() / 2];
        eprintln!("{key}: median relative kernel error {:.1}% over {} tiles", med * 100.0, e.len());
        assert!(med <= 0.10, "{key}: median kernel error {med}");
        // frames have sidecars with the reported positions
        let meta = std::fs::read_to_string(out.join("session/pairs").join(&key).join("pinhole.toml")).unwrap();
        assert!(meta.contains("aperture_mm = -8.0") && meta.contains("frames_averaged = 16"), "{meta}");
    }
    // the flat step: lens.xml carries pa vignetting that reproduces the mock's falloff
    // (lensfun units, r = 1 at half the diagonal) within 0.005 of the centre's brightness
    let xml = std::fs::read_to_string(out.join("lens.xml")).unwrap();
    assert!(xml.contains("<tca model=\"poly3\"") && xml.contains("Measured: vignetting (pa) from the flat field") && xml.contains("minus its dark frame"), "{xml}");
    let k = pa_of(&xml);
    let truth = optics.vignetting.expect("mock.toml states a vignetting").k;
    let v = |k: &[f64; 3], r: f64| 1.0 + k[0] * r * r + k[1] * r.powi(4) + k[2] * r.powi(6);
    let worst = (0..=20).map(|i| i as f64 / 20.0).map(|r| (v(&k, r) - v(&truth, r)).abs()).fold(0.0, f64::max);
    eprintln!("flat field: pa {k:?} vs truth {truth:?}, max |ΔV| {worst:.5}");
    assert!(worst < 0.005, "pa {k:?} vs truth {truth:?}: {worst}");
    // mock.toml's distortion, measured from the pinhole capture: lens.xml carries ptlens whose
    // displacement field is within 0.2 px of the mock's over the frame
    let truth_d = optics.distortion.expect("mock.toml states a distortion");
    assert!(xml.contains("<distortion model=\"ptlens\"") && xml.contains("Measured: distortion (ptlens)"), "{xml}");
    let m = lensrig::target::locate::MeasuredDistortion::load(&out.join("profiles/000-stage-X-20.000")).unwrap().expect("distortion.toml");
    let (max, rms) = lensrig::target::locate::field_difference(&m.ptlens(), &truth_d, 384, 288);
    eprintln!("distortion: ptlens a {:.4} b {:.4} c {:.4} vs truth {truth_d:?}: field error max {max:.3} px, RMS {rms:.3} px", m.a, m.b, m.c);
    assert!(max <= 0.2, "distortion field error {max} px");
    let flat = std::fs::read_to_string(out.join("session/flat/flat.toml")).unwrap();
    assert!(flat.contains("role = \"flat\"") && flat.contains("aperture_mm = -1.0") && flat.contains("stage_mm = -90.0") && flat.contains("frames_averaged = 16"), "{flat}");
    let html = std::fs::read_to_string(out.join("index.html")).unwrap();
    assert!(html.contains("Relative illumination from the flat field") && out.join("report/flat.png").is_file());
    // an existing session is never overwritten
    let e = fails(&["capture", "--rig", rig.to_str().unwrap(), "--out", out.join("session").to_str().unwrap()]);
    assert!(e.contains("already exists") && e.contains("--resume"), "{e}");
    // estimate --session writes one profile per stage position
    let prof = out.join("again");
    ok(&["estimate", "--session", out.join("session").to_str().unwrap(), "--out", prof.to_str().unwrap(), "--quiet", "--kernel", "31"]);
    assert!(prof.join("002-stage-X-60.000/profile.toml").is_file());
    // a second run is refused before any work and leaves the profiles as they were
    let kept = std::fs::read(prof.join("002-stage-X-60.000/profile.toml")).unwrap();
    let e = fails(&["estimate", "--session", out.join("session").to_str().unwrap(), "--out", prof.to_str().unwrap(), "--quiet", "--kernel", "31"]);
    assert!(e.contains("already holds a profile") && e.contains("--force"), "{e}");
    assert_eq!(std::fs::read(prof.join("002-stage-X-60.000/profile.toml")).unwrap(), kept);
    let e = fails(&["estimate", "--session", "s", "--open", "a.png", "--out", "x"]);
    assert!(e.contains("cannot be used with"), "{e}");
    let _ = std::fs::remove_dir_all(&out);
}

/// `k1 k2 k3` of the `<vignetting model="pa">` element of a lensfun file.
fn pa_of(xml: &str) -> [f64; 3] {
    let line = xml.lines().find(|l| l.contains("<vignetting model=\"pa\"")).expect("a vignetting block");
    let attr = |n: &str| -> f64 {
        let i = line.find(&format!(" {n}=\"")).unwrap_or_else(|| panic!("{n} in {line}")) + n.len() + 3;
        line[i..].split('"').next().unwrap().parse().unwrap()
    };
    [attr("k1"), attr("k2"), attr("k3")]
}

/// The flat step is resumable like a pair: an unfinished one (`flat.partial/`) is redone,
/// finished pairs are untouched; without `[plan.flat]` there is no flat field.
#[test]
fn flat_step_is_redone_on_resume_and_optional() {
    let dir = tmp("flat-resume");
    let cfg = config_variant(&dir, |t| t.replace("positions = [-20.0, -40.0, -60.0]", "positions = [-20.0]").replace("frames_to_average = 16", "frames_to_average = 2"));
    let dry = ok(&["capture", "--rig", cfg.to_str().unwrap(), "--out", "/nonexistent/never", "--dry-run"]);
    assert!(dry.contains("flat field: move stage X to -90.000 mm") && dry.contains("capture flat"), "{dry}");
    let s = dir.join("session");
    ok(&["capture", "--rig", cfg.to_str().unwrap(), "--out", s.to_str().unwrap(), "--quiet"]);
    let rec = std::fs::read_to_string(s.join("session.toml")).unwrap();
    assert!(rec.contains("[flat]") && rec.contains("flat = \"flat.png\""), "{rec}");
    let pair = s.join("pairs/000-stage-X-20.000/open.png");
    let before = std::fs::read(&pair).unwrap();
    // as if killed inside the flat step
    std::fs::rename(s.join("flat"), s.join("flat.partial")).unwrap();
    ok(&["capture", "--rig", cfg.to_str().unwrap(), "--out", s.to_str().unwrap(), "--resume", "--quiet"]);
    assert!(s.join("flat/flat.png").is_file() && s.join("flat/dark.toml").is_file() && !s.join("flat.partial").exists());
    let rec = std::fs::read_to_string(s.join("session.toml")).unwrap();
    assert!(rec.contains("status = \"complete\"") && rec.contains("[flat]"), "{rec}");
    assert!(std::fs::read(&pair).unwrap() == before, "a finished pair changed on resume");
    // no [plan.flat]: no flat step
    let cfg2 = config_variant(&dir.join("noflat"), |t| t.replace("positions = [-20.0, -40.0, -60.0]", "positions = [-20.0]").replace("[plan.flat]\nstage_mm = -90.0", ""));
    let s2 = dir.join("s2");
    ok(&["capture", "--rig", cfg2.to_str().unwrap(), "--out", s2.to_str().unwrap(), "--quiet"]);
    assert!(!s2.join("flat").exists() && !std::fs::read_to_string(s2.join("session.toml")).unwrap().contains("[flat]"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn dry_run_lists_moves_and_rejects_out_of_limit_positions() {
    let s = ok(&["capture", "--rig", mock().to_str().unwrap(), "--out", "/nonexistent/never-created", "--dry-run"]);
    assert!(s.contains("move stage X to -40.000 mm") && s.contains("(pinhole)") && s.contains("capture dark"), "{s}");
    assert!(!Path::new("/nonexistent/never-created").exists());
    let dir = tmp("dry");
    let cfg = config_variant(&dir, |t| t.replace("positions = [-20.0, -40.0, -60.0]", "positions = [-20.0, -140.0]"));
    let e = fails(&["capture", "--rig", cfg.to_str().unwrap(), "--out", dir.join("s").to_str().unwrap(), "--dry-run"]);
    assert!(e.contains("axes.stage.positions") && e.contains("-140 mm is outside"), "{e}");
    let ok_msg = ok(&["check-config", mock().to_str().unwrap()]);
    assert!(ok_msg.contains(": ok"), "{ok_msg}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn resume_after_an_interrupted_session_keeps_finished_pairs_byte_identical() {
    let dir = tmp("resume");
    let cfg = config_variant(&dir, |t| t.replace("frames_to_average = 16", "frames_to_average = 2"));
    let s = dir.join("session");
    // each pair takes 4 captures (bracketing test frame, open, pinhole, dark): time out in pair 2
    let o = bin().args(["capture", "--rig", cfg.to_str().unwrap(), "--out", s.to_str().unwrap(), "--quiet"]).env("LENSRIG_MOCK_TIMEOUT_AFTER_CAPTURES", "6").output().unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("camera mock: no frame within"), "{e}");
    let rec = std::fs::read_to_string(s.join("session.toml")).unwrap();
    assert!(rec.contains("status = \"failed: camera mock: no frame"), "{rec}");
    let first = s.join("pairs/000-stage-X-20.000");
    let before: Vec<Vec<u8>> = ["open.png", "open.toml", "pinhole.png", "pinhole.toml", "dark.png"].iter().map(|f| std::fs::read(first.join(f)).unwrap()).collect();
    // the unfinished pair is only in a .partial directory
    assert!(s.join("pairs/001-stage-X-40.000.partial").is_dir() && !s.join("pairs/001-stage-X-40.000").exists());
    // a plain capture into it is refused; --resume finishes it
    fails(&["capture", "--rig", cfg.to_str().unwrap(), "--out", s.to_str().unwrap()]);
    ok(&["capture", "--rig", cfg.to_str().unwrap(), "--out", s.to_str().unwrap(), "--resume", "--quiet"]);
    let rec = std::fs::read_to_string(s.join("session.toml")).unwrap();
    assert!(rec.contains("status = \"complete\"") && rec.contains("resumed = ["), "{rec}");
    let after: Vec<Vec<u8>> = ["open.png", "open.toml", "pinhole.png", "pinhole.toml", "dark.png"].iter().map(|f| std::fs::read(first.join(f)).unwrap()).collect();
    assert!(before == after, "finished pair changed on resume");
    for k in ["000-stage-X-20.000", "001-stage-X-40.000", "002-stage-X-60.000"] {
        assert!(s.join("pairs").join(k).join("pinhole.toml").is_file(), "{k}");
    }
    assert!(!s.join("pairs/001-stage-X-40.000.partial").exists());
    // resuming with a different config is refused
    let other = config_variant(&dir.join("other"), |t| t.replace("frames_to_average = 16", "frames_to_average = 3"));
    let e = fails(&["capture", "--rig", other.to_str().unwrap(), "--out", s.to_str().unwrap(), "--resume"]);
    assert!(e.contains("differs"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The mock rig's pinhole capture (in process, through the mock camera's noise and
/// vignetting) registered to the target file: the fitted ptlens displacement field matches
/// the configured one within 0.2 px everywhere on the 384 × 288 frame (17 × 13 grid, corners
/// included), and with no distortion configured the fitted field stays under 0.1 px.
#[test]
fn locate_recovers_the_mock_distortion_from_the_pinhole_capture() {
    use lensrig::optics::distortion::PtLens;
    use lensrig::rig::camera::mock::MockCamera;
    use lensrig::rig::camera::Camera;
    use lensrig::rig::controller::Position;
    use lensrig::target::locate::{field_difference, locate, LocateOptions, Nominal};
    use lensrig::target::TargetSpec;
    use std::sync::{Arc, Mutex};
    let dir = tmp("locate");
    for (k, truth, tol) in [("none", PtLens::NONE, 0.1), ("barrel", PtLens { a: 0.0, b: -0.02, c: 0.0 }, 0.2), ("wavy", PtLens { a: 0.01, b: -0.03, c: 0.005 }, 0.2)] {
        let line = format!("distortion = [{}, {}, {}]", truth.a, truth.b, truth.c);
        let cfg = config::load(&config_variant(&dir.join(k), |t| t.lines().filter(|l| !l.starts_with("distortion =")).map(|l| format!("{l}\n")).collect::<String>() + &line)).unwrap();
        let pos = Arc::new(Mutex::new(Position::ZERO));
        let mut cam = MockCamera::new(&cfg, pos.clone()).unwrap();
        let o = cam.optics().clone();
        assert_eq!(o.distortion, Some(truth));
        let stage = cfg.axes.stage.positions[0];
        pos.lock().unwrap().set(o.aperture_axis, o.aperture_pinhole);
        pos.lock().unwrap().set(o.stage_axis, stage);
        cam.set_exposure(cfg.camera.exposure_us * 16).unwrap();
        let f = cam.capture(16).unwrap();
        let g = &f.image.planes[1];
        let target = TargetSpec::load(&cfg.target.as_ref().unwrap().path).unwrap();
        let (u0, v0) = o.target_origin(stage);
        // the rig's magnification known to 4 %
        let nominal = Nominal { pixels_per_cell: o.pixels_per_cell * 0.96, u0, v0 };
        let fit = locate(g, &target, &nominal, &LocateOptions::default()).unwrap();
        let (max, rms) = field_difference(&fit.ptlens, &truth, g.width, g.height);
        let corner = truth.displacement_px(0.0, 0.0, g.width, g.height);
        eprintln!(
            "{k}: truth {truth:?} (corner {:.2} px), fit a {:.4} b {:.4} c {:.4}; field error max {max:.3} px, RMS {rms:.3} px; {} of {} tiles, residual {:.3} px",
            corner.0.hypot(corner.1), fit.ptlens.a, fit.ptlens.b, fit.ptlens.c, fit.tiles_used, fit.tiles.len(), fit.rms_residual_px
        );
        assert!(max <= tol, "{k}: field error {max} px > {tol}");
        assert!(fit.tiles_used >= 60, "{k}: {} tiles", fit.tiles_used);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// A rig that is not the mock states where the target sits on the sensor (`[target.layout]`);
/// `calibrate` registers from there. Here the mock rig is given a layout that is 3 % off in
/// scale and 1–1.5 cells off in position: the distortion is still measured (against the
/// mock's truth, within 0.2 px over the frame). A layout far off (2× the scale) is reported as
/// not measured, and the calibration still completes. A bad layout value is refused by name.
#[test]
fn calibrate_measures_distortion_from_the_configured_target_layout() {
    let dir = tmp("layout");
    let base = |t: String| t.replace("positions = [-20.0, -40.0, -60.0]", "positions = [-20.0]").replace("frames_to_average = 16", "frames_to_average = 2").replace("[plan.flat]\nstage_mm = -90.0", "");
    // the mock's own layout: pixels_per_cell 1.6, cell (7 − stage·1.0, 5) at pixel (0, 0)
    let layout = |ppc: f64, u: f64, v: f64| format!("\n[target.layout]\npixels_per_cell = {ppc}\norigin = [{u}, {v}]\ncells_per_mm = 1.0\n");
    let with_layout = |name: &str, ppc: f64, u: f64, v: f64| config_variant(&dir.join(name), |t| base(t) + &layout(ppc, u, v));
    let cfg = with_layout("near", 1.55, 8.5, 4.0);
    assert!(std::fs::read_to_string(&cfg).unwrap().contains("[target.layout]"), "the variant did not take");
    let out = dir.join("near-out");
    ok(&["calibrate", "--rig", cfg.to_str().unwrap(), "--out", out.to_str().unwrap(), "--quiet"]);
    let s: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let d = &s["distortion"];
    let max = d["field_error_max_px"].as_f64().unwrap_or_else(|| panic!("no distortion measured: {d}"));
    eprintln!("layout 3 % off: ptlens a {} b {} c {}, field error max {max:.3} px", d["a"], d["b"], d["c"]);
    assert!(max <= 0.2, "{d}");
    assert!(std::fs::read_to_string(out.join("lens.xml")).unwrap().contains("<distortion model=\"ptlens\""));
    // far off: not measured, not fatal
    let far = with_layout("far", 3.2, 8.5, 4.0);
    let out2 = dir.join("far-out");
    ok(&["calibrate", "--rig", far.to_str().unwrap(), "--out", out2.to_str().unwrap(), "--quiet"]);
    let s2: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out2.join("summary.json")).unwrap()).unwrap();
    assert!(s2["distortion"]["error"].as_str().is_some_and(|e| e.contains("target not found")), "{}", s2["distortion"]);
    assert!(!std::fs::read_to_string(out2.join("lens.xml")).unwrap().contains("<distortion"));
    assert!(std::fs::read_to_string(out2.join("index.html")).unwrap().contains("Not measured: target not found"));
    // bad values and unknown keys are refused, naming the key
    let bad = with_layout("bad", -1.0, 8.5, 4.0);
    let e = fails(&["check-config", bad.to_str().unwrap()]);
    assert!(e.contains("target.layout.pixels_per_cell"), "{e}");
    let unknown = config_variant(&dir.join("unknown"), |t| base(t) + &layout(1.6, 7.0, 5.0) + "scale = 2\n");
    let e = fails(&["check-config", unknown.to_str().unwrap()]);
    assert!(e.contains("scale"), "{e}");
    // and `calibrate` refuses it before anything is created: no empty --out is left behind
    let never = dir.join("never-created");
    let e = fails(&["calibrate", "--rig", unknown.to_str().unwrap(), "--out", never.to_str().unwrap(), "--quiet"]);
    assert!(e.contains("scale"), "{e}");
    assert!(!never.exists(), "a refused config left {} behind", never.display());
    let _ = std::fs::remove_dir_all(&dir);
}

/// A stage that refocuses (`[axes.stage] focus_distance_m`): `calibrate` collects its
/// calibrations as one profile set keyed like lensfun, which `deblur --distance` reads (here
/// between the two calibrations, so it blends them and says so). The mock's stage slides the
/// target rather than refocusing, so this checks the set's plumbing; interpolation accuracy
/// against a held-out calibration is `profile::set`'s test. A count that does not match the
/// positions is refused by key.
#[test]
fn calibrate_collects_a_refocusing_stage_as_a_profile_set() {
    let dir = tmp("set");
    let edit = |t: String, d: &str| {
        t.replace("positions = [-20.0, -40.0, -60.0]", &format!("positions = [-20.0, -40.0]\nfocus_distance_m = {d}"))
            .replace("frames_to_average = 16", "frames_to_average = 2")
            .replace("[plan.flat]\nstage_mm = -90.0", "")
    };
    let cfg = config_variant(&dir, |t| edit(t, "[0.7, 0.9]"));
    let out = dir.join("out");
    ok(&["calibrate", "--rig", cfg.to_str().unwrap(), "--out", out.to_str().unwrap(), "--quiet"]);
    let set = lensrig::profile::set::ProfileSet::load(&out.join("profiles")).unwrap();
    let got: Vec<(f64, f64, &str)> = set.calibration.iter().map(|c| (c.distance, c.aperture, c.profile.as_str())).collect();
    assert_eq!(got, vec![(0.7, 5.6, "000-stage-X-20.000"), (0.9, 5.6, "001-stage-X-40.000")]);
    assert!(set.calibration.iter().all(|c| c.focal > 0.0));
    assert!(std::fs::read_to_string(out.join("index.html")).unwrap().contains("profiles/index.toml"));
    let photo = out.join("session/pairs/000-stage-X-20.000/open.png");
    let restored = dir.join("restored.png");
    let o = common::run(&["deblur", "--profile", out.join("profiles").to_str().unwrap(), "--distance", "0.8", "--aperture", "5.6", "--in", photo.to_str().unwrap(), "--out", restored.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("interpolated") && restored.is_file(), "{err}");
    let bad = config_variant(&dir.join("bad"), |t| edit(t, "[0.7]"));
    let e = fails(&["check-config", bad.to_str().unwrap()]);
    assert!(e.contains("axes.stage.focus_distance_m"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
