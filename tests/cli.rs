//! End-to-end tests of the real binary in temporary directories (ripgrep's `tests/util.rs`
//! style): simulated calibration → estimate → profile → simulate, and the error paths.

mod common;

use common::{fails_one_line, ok};
use std::path::Path;

fn summary(dir: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).unwrap()).unwrap()
}

/// The core figure: kernels recovered from an ideal pinhole reference are within 10% (median
/// relative L2) of the simulator's truth at the tile centres, and the profile predicts an
/// independent pair. Also exercises `simulate` on the demo's files.
#[test]
fn demo_recovers_the_simulated_lens_and_simulate_predicts() {
    let d = tempfile::tempdir().unwrap();
    let run = d.path().join("run");
    let run_s = run.to_str().unwrap();
    // the demo's defaults: 512×384, f/5.6, the tool's own kernel size and PSF grid
    ok(&["demo", "--out", run_s, "--quiet"]);
    let s = summary(&run);
    let med = s["median_relative_error"].as_f64().unwrap();
    assert!(med <= 0.10, "median kernel error {med}");
    let cv = s["cross_validation"]["ratio"].as_f64().unwrap();
    // the goal: the profile predicts an independent pair to within 1.10× the noise
    assert!(cv <= 1.10, "cross-validation residual/noise {cv}");
    assert!(cv > 0.9, "a prediction better than the noise floor means the truth leaked: {cv}");

    let text = std::fs::read_to_string(run.join("profile/profile.toml")).unwrap();
    for key in ["[psf]", "kernel_size", "columns", "rows", "centers"] {
        assert!(text.contains(key), "profile.toml lacks {key}");
    }
    for c in ["R", "G", "B"] {
        assert!(run.join(format!("profile/psf-{c}.tiff")).exists());
    }
    // simulate: same size, 16-bit, and close to the recorded wide-open image
    let pred = d.path().join("pred.png");
    ok(&["simulate", "--profile", run.join("profile").to_str().unwrap(), "--sharp", run.join("pinhole.png").to_str().unwrap(), "--out", pred.to_str().unwrap()]);
    // an existing output is never replaced without --force, and is left as it was
    let before = std::fs::read(&pred).unwrap();
    let e = fails_one_line(&["simulate", "--profile", run.join("profile").to_str().unwrap(), "--sharp", run.join("pinhole.png").to_str().unwrap(), "--out", pred.to_str().unwrap()]);
    assert!(e.contains("already exists") && e.contains("--force"), "{e}");
    assert_eq!(std::fs::read(&pred).unwrap(), before);
    // estimate never replaces a profile without --force (a hand-edited or cited profile), and
    // leaves it byte for byte; with --force it writes a fresh one
    let prof = run.join("profile");
    let toml_before = std::fs::read(prof.join("profile.toml")).unwrap();
    let (open_s, pin_s, prof_s) = (run.join("open.png"), run.join("pinhole.png"), prof.to_str().unwrap().to_string());
    let args = ["estimate", "--open", open_s.to_str().unwrap(), "--pinhole", pin_s.to_str().unwrap(), "--out", &prof_s, "--quiet"];
    let e = fails_one_line(&args);
    assert!(e.contains("already holds a profile") && e.contains("--force"), "{e}");
    assert_eq!(std::fs::read(prof.join("profile.toml")).unwrap(), toml_before);
    ok(&[&args[..], &["--force"]].concat());
    let replaced = std::fs::read_to_string(prof.join("profile.toml")).unwrap();
    assert!(replaced.contains(open_s.to_str().unwrap()), "--force writes the new estimate's profile: {replaced}");
    let p = lensrig::image::io::read_image(&pred).unwrap();
    let o = lensrig::image::io::read_image(&run.join("open.png")).unwrap();
    assert_eq!((p.width(), p.height(), p.channel_count(), p.format), (512, 384, 3, lensrig::image::SampleFormat::U16));
    let g = 1;
    let mut se = 0.0;
    let mut n = 0.0;
    for y in 20..268 {
        for x in 20..364 {
            se += ((p.planes[g].get(x, y) - o.planes[g].get(x, y)) as f64).powi(2);
            n += 1.0;
        }
    }
    let rms = (se / n).sqrt();
    assert!(rms < 0.02, "prediction RMS {rms}");
}

#[test]
fn errors_are_one_line_and_name_the_file() {
    let d = tempfile::tempdir().unwrap();
    let a = d.path().join("a.png");
    let b = d.path().join("b.png");
    let img = |w, h| lensrig::image::Image::new(vec![lensrig::image::Plane::filled(w, h, 0.5)]);
    lensrig::image::io::write_png16(&a, &img(64, 48), lensrig::fsutil::Overwrite::Never).unwrap();
    lensrig::image::io::write_png16(&b, &img(60, 48), lensrig::fsutil::Overwrite::Never).unwrap();
    let out = d.path().join("prof");
    let e = fails_one_line(&["estimate", "--open", a.to_str().unwrap(), "--pinhole", b.to_str().unwrap(), "--out", out.to_str().unwrap(), "--quiet"]);
    assert!(e.contains("b.png") && e.contains("60x48"), "{e}");
    let e = fails_one_line(&["estimate", "--open", a.to_str().unwrap(), "--pinhole", a.to_str().unwrap(), "--out", out.to_str().unwrap(), "--kernel", "8"]);
    assert!(e.contains("odd"), "{e}");
    let e = fails_one_line(&["simulate", "--profile", d.path().join("nope").to_str().unwrap(), "--sharp", a.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert!(e.contains("profile.toml"), "{e}");
    let e = fails_one_line(&["deblur", "--profile", d.path().join("nope").to_str().unwrap(), "--in", a.to_str().unwrap(), "--out", out.to_str().unwrap(), "--tile", "8"]);
    assert!(e.contains("--tile 8") && e.contains("16"), "{e}");
    assert!(!out.exists(), "nothing is written on error");
}

#[test]
fn target_writes_a_printable_page_and_never_overwrites() {
    let d = tempfile::tempdir().unwrap();
    let t = d.path().join("t");
    let msg = ok(&["target", "--out", t.to_str().unwrap(), "--paper", "A5", "--dpi", "150"]);
    assert!(msg.contains("150 DPI"), "{msg}");
    let png = image::open(d.path().join("t.png")).unwrap();
    // A5 landscape at 150 DPI
    assert_eq!((png.width(), png.height()), (1240, 874));
    let before = std::fs::read(d.path().join("t.png")).unwrap();
    let e = fails_one_line(&["target", "--out", t.to_str().unwrap(), "--paper", "A5", "--dpi", "150", "--seed", "9"]);
    assert!(e.contains("already exists"), "{e}");
    assert_eq!(std::fs::read(d.path().join("t.png")).unwrap(), before);
}
