//! The lensfun export read back by the real consumer: `lensrig export lensfun` on a synthetic
//! R, G, B profile with known lateral colour and a flat field with known falloff; the file is
//! loaded by liblensfun (a small C probe compiled against the system's lensfun, Debian's
//! `liblensfun-dev` 0.3.3), the lens is looked up, and lensfun's TCA and vignetting corrections
//! are compared with lensrig's own measurements. Without a C compiler or lensfun the round trip
//! is skipped with a message (run with `--nocapture` to see it); the XML checks always run.

mod common;

use lensrig::export::lensfun::{tca_norm, vignetting_norm};
use lensrig::optics::distortion::PtLens;
use lensrig::rig::camera::mock::MockOptics;
use lensrig::target::locate::MeasuredDistortion;
use lensrig::fsutil::Overwrite;
use lensrig::image::io::write_png16;
use lensrig::image::filter::pixel_gaussian as gaussian;
use lensrig::image::{Image, Plane, SampleFormat, Transfer};
use lensrig::optics::psf_grid::PsfGrid;
use lensrig::profile::{Profile, PsfTable, SourceInfo};
use std::io::Write;
use std::path::Path;
use std::process::{Command, Stdio};

const W: usize = 384;
const H: usize = 288;
// truth, in lensfun's units: r_d = r_u·(v + c·r + b·r²)
const RED: [f64; 3] = [1.0012, 0.0, 0.0009];
const BLUE: [f64; 3] = [0.9992, -0.0004, 0.0];
const VIG: [f64; 3] = [-0.25, 0.03, 0.0];

fn shift_of(p: &[f64; 3], x: f64, y: f64) -> (f64, f64) {
    let (cx, cy) = ((W as f64 - 1.0) / 2.0, (H as f64 - 1.0) / 2.0);
    let r = (x - cx).hypot(y - cy) * tca_norm(W, H);
    let m = p[0] + p[1] * r + p[2] * r * r - 1.0;
    ((x - cx) * m, (y - cy) * m)
}

fn falloff(x: f64, y: f64) -> f64 {
    let (cx, cy) = ((W as f64 - 1.0) / 2.0, (H as f64 - 1.0) / 2.0);
    let r2 = ((x - cx).powi(2) + (y - cy).powi(2)) * vignetting_norm(W, H).powi(2);
    1.0 + VIG[0] * r2 + VIG[1] * r2 * r2 + VIG[2] * r2 * r2 * r2
}

fn write_inputs(dir: &Path) -> PsfGrid {
    let (cols, rows, k) = (7, 5, 17);
    let centers = PsfGrid::regular_centers(W, H, cols, rows);
    let mut kernels = vec![Vec::new(), Vec::new(), Vec::new()];
    for &[x, y] in &centers {
        let (rx, ry) = shift_of(&RED, x, y);
        let (bx, by) = shift_of(&BLUE, x, y);
        kernels[0].push(gaussian(k, 1.6, rx, ry));
        kernels[1].push(gaussian(k, 1.4, 0.0, 0.0));
        kernels[2].push(gaussian(k, 1.9, bx, by));
    }
    let channels: Vec<String> = ["R", "G", "B"].iter().map(|s| s.to_string()).collect();
    let grid = PsfGrid { kernel_size: k, columns: cols, rows, centers: centers.clone(), channels: channels.clone(), kernels };
    let psf = PsfTable { kernel_size: k, columns: cols, rows, centers, tile_size: None, files: Default::default() };
    let source = SourceInfo { width: W, height: H, channels, sample_format: SampleFormat::U16, transfer: Transfer::Linear, open: None, pinhole: None, black_level: vec![] };
    Profile { meta: Profile::new_meta(source, vec![1.0; 3], psf), grid: grid.clone() }.save(&dir.join("profile")).expect("profile");
    let flat = Plane::from_fn(W, H, |x, y| (0.7 * falloff(x as f64, y as f64)) as f32);
    write_png16(&dir.join("flat.png"), &Image::new(vec![flat.clone(), flat.clone(), flat]), Overwrite::Replace).expect("flat");
    grid
}

fn lensrig(args: &[&str]) -> String {
    let o = Command::new(env!("CARGO_BIN_EXE_lensrig")).args(args).output().expect("run lensrig");
    assert!(o.status.success(), "{args:?}: {}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).to_string()
}

/// Compiles tests/lensfun/probe.c against the system's lensfun; `Err(reason)` to skip.
fn build_probe(dir: &Path) -> Result<std::path::PathBuf, String> {
    let header = Path::new("/usr/include/lensfun/lensfun.h");
    if !header.is_file() {
        return Err(format!("{} not found (apt-get install liblensfun-dev)", header.display()));
    }
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/lensfun/probe.c");
    let exe = dir.join("probe");
    let o = Command::new("cc")
        .args([src.to_str().unwrap_or_default(), "-O1", "-I/usr/include/lensfun", "-llensfun", "-lm", "-o"])
        .arg(&exe)
        .output()
        .map_err(|e| format!("no C compiler (cc): {e}"))?;
    if !o.status.success() {
        return Err(format!("probe does not compile against lensfun: {}", String::from_utf8_lossy(&o.stderr)));
    }
    Ok(exe)
}

#[test]
fn lensfun_reads_the_export_and_corrects_like_lensrig() {
    let d = tempfile::tempdir().expect("tempdir");
    let grid = write_inputs(d.path());
    let xml = d.path().join("lens.xml");
    let (p, f, x) = (d.path().join("profile"), d.path().join("flat.png"), xml.clone());
    let args = ["export", "lensfun", "--profile", p.to_str().unwrap_or_default(), "--flat", f.to_str().unwrap_or_default(), "--out", x.to_str().unwrap_or_default(), "--model", "Test singlet", "--focal-mm", "16", "--crop-factor", "18", "--aperture", "5.6"];
    let out = lensrig(&args);
    assert!(out.contains("tca") && out.contains("vignetting"), "{out}");
    let text = std::fs::read_to_string(&xml).expect("xml");
    assert!(text.contains("<lensdatabase version=\"1\">") && text.contains("<tca model=\"poly3\"") && text.contains("<vignetting model=\"pa\""), "{text}");
    assert!(!text.contains("<distortion"), "distortion is not measured: {text}");
    assert!(text.contains("Not measured: distortion") && text.contains("Measured: vignetting"), "{text}");
    // never overwrites without --force
    let o = Command::new(env!("CARGO_BIN_EXE_lensrig")).args(args).output().expect("run");
    assert!(!o.status.success());
    // without a flat field: no vignetting block
    let x2 = d.path().join("no-flat.xml");
    lensrig(&["export", "lensfun", "--profile", p.to_str().unwrap_or_default(), "--out", x2.to_str().unwrap_or_default(), "--focal-mm", "16", "--crop-factor", "18"]);
    let t2 = std::fs::read_to_string(&x2).expect("xml");
    assert!(t2.contains("<tca") && !t2.contains("<vignetting"), "{t2}");

    let probe = match build_probe(d.path()) {
        Ok(p) => p,
        Err(why) => {
            eprintln!("SKIPPED the lensfun round trip: {why}");
            println!("SKIPPED the lensfun round trip: {why}");
            return;
        }
    };
    // every tile centre, plus the corners and the centre
    let mut pts: Vec<(f64, f64)> = grid.centers.iter().map(|c| (c[0], c[1])).collect();
    pts.extend([(0.0, 0.0), (W as f64 - 1.0, H as f64 - 1.0), ((W as f64 - 1.0) / 2.0, (H as f64 - 1.0) / 2.0)]);
    let stdout = run_probe(&probe, &x, "Test singlet", "18", (W, H), &pts);
    assert!(stdout.contains("flags tca=1 vignetting=1"), "lensfun did not apply both corrections: {stdout}");
    let (mut tca_err, mut vig_err, mut n_tca, mut n_vig) = (0.0f64, 0.0f64, 0, 0);
    for line in stdout.lines() {
        let v: Vec<f64> = line.split_whitespace().skip(1).filter_map(|s| s.parse().ok()).collect();
        if line.starts_with("tca ") && v.len() == 6 {
            // lensrig's own: the measured lateral colour (centroid offsets) at this position,
            // which for this synthetic profile is the truth it was built with
            let (x, y) = (v[0], v[1]);
            let (rx, ry) = shift_of(&RED, x, y);
            let (bx, by) = shift_of(&BLUE, x, y);
            for (got, want) in [(v[2] - x, rx), (v[3] - y, ry), (v[4] - x, bx), (v[5] - y, by)] {
                tca_err = tca_err.max((got - want).abs());
            }
            n_tca += 1;
        } else if line.starts_with("vig ") && v.len() == 3 {
            // lensfun's gain times the captured falloff must flatten the field
            vig_err = vig_err.max((v[2] * falloff(v[0], v[1]) - 1.0).abs());
            n_vig += 1;
        }
    }
    println!("lensfun round trip at {n_tca} points: max TCA displacement error {tca_err:.4} px, max vignetting residual {:.3} %", vig_err * 100.0);
    assert_eq!((n_tca, n_vig), (pts.len(), pts.len()), "{stdout}");
    assert!(tca_err < 0.02, "TCA: lensfun's correction differs from lensrig's by {tca_err} px");
    assert!(vig_err < 0.005, "vignetting: lensfun leaves {vig_err} of falloff");
}

/// `calibrate` on a mock rig with a flat step writes `lens.xml`; liblensfun loads it and its
/// vignetting correction flattens the mock's true falloff (`[lens] vignetting`) within 0.5 %
/// at the centre, the tile grid's corners and the image corners; its distortion correction
/// (measured from the pinhole capture) agrees with the mock's true ptlens within 0.2 px.
#[test]
fn calibrate_with_a_flat_step_exports_vignetting_lensfun_applies() {
    let d = tempfile::tempdir().expect("tempdir");
    let cfg = common::mock_config(d.path(), |t| t.replace("positions = [-20.0, -40.0, -60.0]", "positions = [-20.0]"));
    let out = d.path().join("run");
    lensrig(&["calibrate", "--rig", cfg.to_str().unwrap_or_default(), "--out", out.to_str().unwrap_or_default(), "--quiet"]);
    let xml = out.join("lens.xml");
    let text = std::fs::read_to_string(&xml).expect("lens.xml");
    assert!(text.contains("<vignetting model=\"pa\" focal=\"16\" aperture=\"5.6\" distance=\"1000\""), "{text}");
    let rig = lensrig::rig::config::load(&cfg).expect("config");
    let truth = MockOptics::from_config(&rig).expect("optics").vignetting.expect("a stated vignetting");
    let probe = match build_probe(d.path()) {
        Ok(p) => p,
        Err(why) => {
            eprintln!("SKIPPED the lensfun round trip of calibrate's lens.xml: {why}");
            println!("SKIPPED the lensfun round trip of calibrate's lens.xml: {why}");
            return;
        }
    };
    let crop = text.lines().find_map(|l| l.trim().strip_prefix("<cropfactor>")).and_then(|l| l.strip_suffix("</cropfactor>")).expect("cropfactor").to_string();
    let pts = [(0.0, 0.0), (383.0, 287.0), (191.5, 143.5), (0.0, 143.5), (191.5, 0.0), (300.0, 50.0), (50.0, 250.0)];
    let stdout = run_probe(&probe, &xml, "Simple lens", &crop, (384, 288), &pts);
    assert!(stdout.contains("vignetting=1"), "probe: {stdout}");
    let mut worst = 0.0f64;
    let mut n = 0;
    for line in stdout.lines().filter(|l| l.starts_with("vig ")) {
        let v: Vec<f64> = line.split_whitespace().skip(1).filter_map(|s| s.parse().ok()).collect();
        worst = worst.max((v[2] * truth.gain(v[0], v[1], 384, 288) - 1.0).abs());
        n += 1;
    }
    println!("calibrate's lens.xml through liblensfun: max vignetting residual against the mock's truth {:.3} % at {n} points", worst * 100.0);
    assert_eq!(n, pts.len(), "{stdout}");
    assert!(worst < 0.005, "lensfun leaves {worst} of the mock's falloff");
    // the distortion measured from the pinhole capture, applied by lensfun, puts every point
    // within 0.2 px of where the mock's true ptlens puts it
    let dist = MockOptics::from_config(&rig).expect("optics").distortion.expect("mock.toml states a distortion");
    let mut dworst = 0.0f64;
    let mut nd = 0;
    for line in stdout.lines().filter(|l| l.starts_with("dist ")) {
        let v: Vec<f64> = line.split_whitespace().skip(1).filter_map(|s| s.parse().ok()).collect();
        let (x, y) = dist.distort_px(v[0], v[1], 384, 288);
        dworst = dworst.max((v[2] - x).hypot(v[3] - y));
        nd += 1;
    }
    println!("calibrate's lens.xml through liblensfun: max distortion error against the mock's truth {dworst:.3} px at {nd} points");
    assert!(nd == pts.len() && dworst <= 0.2, "lensfun's distortion differs from the mock's truth by {dworst} px ({nd} points)");
}

/// Runs the probe on `xml` for lens `model` on a `size` image at `pts` (16 mm, f/5.6,
/// 1000 m); its stdout.
fn run_probe(probe: &Path, xml: &Path, model: &str, crop: &str, size: (usize, usize), pts: &[(f64, f64)]) -> String {
    let mut child = Command::new(probe)
        .args([xml.to_str().unwrap_or_default(), "lensrig", model, crop, &size.0.to_string(), &size.1.to_string(), "16", "5.6", "1000"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("probe");
    {
        let mut stdin = child.stdin.take().expect("stdin");
        for (x, y) in pts {
            writeln!(stdin, "{x} {y}").expect("write");
        }
    }
    let o = child.wait_with_output().expect("probe output");
    let stdout = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(o.status.success(), "probe: {} {}", stdout, String::from_utf8_lossy(&o.stderr));
    stdout
}

/// A profile holding a distortion measurement exports `<distortion model="ptlens">`, and
/// liblensfun's distortion correction maps every corrected pixel of a 13 × 9 grid (corners
/// included) to the sensor position lensrig's ptlens model gives, within 0.05 px; lensrig's
/// own undistortion of that position returns the grid point within 0.05 px.
#[test]
fn lensfun_applies_the_exported_distortion_like_lensrig() {
    let d = tempfile::tempdir().expect("tempdir");
    write_inputs(d.path());
    let truth = PtLens { a: 0.004, b: -0.02, c: 0.003 };
    let rec = MeasuredDistortion {
        model: "ptlens".into(),
        a: truth.a,
        b: truth.b,
        c: truth.c,
        width: W,
        height: H,
        measured: "2026-01-01T00:00:00Z".into(),
        capture: "pinhole.png".into(),
        target: "target.toml".into(),
        tiles_used: 88,
        tiles_total: 88,
        rms_residual_px: 0.01,
        pixels_per_cell: 1.6,
        rotation_deg: 0.0,
    };
    let (p, x) = (d.path().join("profile"), d.path().join("lens.xml"));
    rec.save(&p).expect("distortion.toml");
    let out = lensrig(&["export", "lensfun", "--profile", p.to_str().unwrap_or_default(), "--out", x.to_str().unwrap_or_default(), "--model", "Test singlet", "--focal-mm", "16", "--crop-factor", "18"]);
    assert!(out.contains("distortion,") && !out.contains("no distortion"), "{out}");
    let text = std::fs::read_to_string(&x).expect("xml");
    assert!(text.contains("<distortion model=\"ptlens\" focal=\"16\" a=\"0.004\" b=\"-0.02\" c=\"0.003\" />") && text.contains("Measured: distortion (ptlens) at 2026-01-01T00:00:00Z"), "{text}");
    assert!(text.find("<distortion").unwrap_or(usize::MAX) < text.find("<tca").unwrap_or(0), "XSD order: distortion before tca");
    // another sensor size is refused
    let mut other = rec.clone();
    other.width = 640;
    other.save(&p).expect("distortion.toml");
    let o = Command::new(env!("CARGO_BIN_EXE_lensrig")).args(["export", "lensfun", "--profile", p.to_str().unwrap_or_default(), "--out", d.path().join("x.xml").to_str().unwrap_or_default(), "--focal-mm", "16", "--crop-factor", "18"]).output().expect("run");
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("640x288"), "{}", String::from_utf8_lossy(&o.stderr));
    let probe = match build_probe(d.path()) {
        Ok(p) => p,
        Err(why) => {
            eprintln!("SKIPPED the lensfun distortion round trip: {why}");
            println!("SKIPPED the lensfun distortion round trip: {why}");
            return;
        }
    };
    let pts: Vec<(f64, f64)> = (0..=8).flat_map(|j| (0..=12).map(move |i| (i as f64 * (W as f64 - 1.0) / 12.0, j as f64 * (H as f64 - 1.0) / 8.0))).collect();
    let stdout = run_probe(&probe, &x, "Test singlet", "18", (W, H), &pts);
    assert!(stdout.contains("distortion=1"), "lensfun did not apply the distortion: {stdout}");
    let (mut fwd, mut back, mut shift, mut n) = (0.0f64, 0.0f64, 0.0f64, 0);
    for line in stdout.lines().filter(|l| l.starts_with("dist ")) {
        let v: Vec<f64> = line.split_whitespace().skip(1).filter_map(|s| s.parse().ok()).collect();
        let (xd, yd) = truth.distort_px(v[0], v[1], W, H);
        fwd = fwd.max((v[2] - xd).hypot(v[3] - yd));
        let (xu, yu) = truth.undistort_px(v[2], v[3], W, H);
        back = back.max((xu - v[0]).hypot(yu - v[1]));
        shift = shift.max((v[2] - v[0]).hypot(v[3] - v[1]));
        n += 1;
    }
    println!("lensfun distortion at {n} points: max |lensfun − lensrig| {fwd:.4} px, lensrig's undistortion of lensfun's position {back:.4} px (largest displacement {shift:.2} px)");
    assert_eq!(n, pts.len(), "{stdout}");
    assert!(shift > 2.0, "the test distortion is too weak to test anything: {shift} px");
    assert!(fwd <= 0.05 && back <= 0.05, "lensfun and lensrig differ: {fwd} / {back} px");
}
