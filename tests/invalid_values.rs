//! NaN, Inf and negative values in every input role through the real binary: the wide-open
//! and pinhole captures (`estimate`), the photo (`deblur`) and the sharp image (`simulate`).
//! Non-finite values are refused by default with the file and the pixel named; with
//! `--mask-invalid` they are excluded from the data term and the result on the remaining
//! pixels matches the clean run; negative values are legal, and many of them are reported.
//! A pair stored at two sample depths (8-bit and 16-bit) is accepted with a note naming the
//! coarser file.

use lensrig::image::{Plane, SampleFormat};
use lensrig::optics::psf_grid::PsfGrid;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const W: usize = 96;
const H: usize = 96;

fn lensrig(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_lensrig")).args(args).output().expect("run lensrig")
}

fn ok(args: &[&str]) -> String {
    let o = lensrig(args);
    assert!(o.status.success(), "lensrig {args:?} failed: {}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn refused(args: &[&str]) -> String {
    let o = lensrig(args);
    let e = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(o.status.code(), Some(2), "lensrig {args:?} should exit 2: {e}");
    assert_eq!(e.trim_end().lines().count(), 1, "one line: {e}");
    e
}

/// A float TIFF written with the raw encoder (lensrig's writer refuses NaN).
fn write_tiff(path: &Path, p: &Plane) {
    let f = std::fs::File::create(path).unwrap();
    let mut enc = tiff::encoder::TiffEncoder::new(std::io::BufWriter::new(f)).unwrap();
    enc.write_image::<tiff::encoder::colortype::Gray32Float>(p.width as u32, p.height as u32, &p.data).unwrap();
}

/// A random two-level noise target (cells of 2 px), like the printed calibration target.
fn sharp() -> Plane {
    let mut rng = lensrig::rng::Rng::new(7);
    let cells: Vec<f32> = (0..(W / 2) * (H / 2)).map(|_| if rng.uniform() < 0.5 { 0.15 } else { 0.75 }).collect();
    Plane::from_fn(W, H, |x, y| cells[(y / 2) * (W / 2) + x / 2])
}

/// The blur: a 5×5 kernel, the same everywhere.
fn truth() -> PsfGrid {
    let k = Plane::from_fn(5, 5, |x, y| {
        let (dx, dy) = (x as f32 - 2.0, y as f32 - 2.0);
        (-(dx * dx + 0.6 * dy * dy) / 2.5).exp()
    });
    let s = k.sum() as f32;
    let k = k.map(|v| v / s);
    PsfGrid { kernel_size: 5, columns: 1, rows: 1, centers: vec![[W as f64 / 2.0 - 0.5, H as f64 / 2.0 - 0.5]], channels: vec!["Y".into()], kernels: vec![vec![k]] }
}

struct Files {
    dir: tempfile::TempDir,
}

impl Files {
    fn new() -> Self {
        let f = Files { dir: tempfile::tempdir().unwrap() };
        let pin = sharp();
        let open = lensrig::optics::forward::blur_channel(&pin, &truth(), 0);
        write_tiff(&f.p("open.tiff"), &open);
        write_tiff(&f.p("pinhole.tiff"), &pin);
        f
    }
    fn p(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }
    fn s(&self, name: &str) -> String {
        self.p(name).to_str().unwrap().to_string()
    }
    /// A copy of `from` with `v` at the listed pixels.
    fn damaged(&self, from: &str, to: &str, v: f32, at: &[(usize, usize)]) -> String {
        let mut img = lensrig::image::io::read_image(&self.p(from)).unwrap().planes.remove(0);
        for &(x, y) in at {
            img.set(x, y, v);
        }
        write_tiff(&self.p(to), &img);
        self.s(to)
    }
    fn estimate(&self, open: &str, pinhole: &str, out: &str, extra: &[&str]) -> Output {
        let mut a = vec!["estimate", "--open", open, "--pinhole", pinhole, "--out", out, "--kernel", "5", "--tile", "48", "--quiet", "--register", "none"];
        a.extend_from_slice(extra);
        lensrig(&a)
    }
}

fn kernels(dir: &Path) -> Vec<f32> {
    let p = lensrig::profile::Profile::load(dir).unwrap();
    p.grid.kernels.iter().flatten().flat_map(|k| k.data.clone()).collect()
}

fn rel_l2(a: &[f32], b: &[f32]) -> f64 {
    let num: f64 = a.iter().zip(b).map(|(x, y)| ((x - y) as f64).powi(2)).sum();
    let den: f64 = b.iter().map(|y| (*y as f64).powi(2)).sum();
    (num / den).sqrt()
}

const BAD: [(&str, f32); 2] = [("NaN", f32::NAN), ("Inf", f32::INFINITY)];

#[test]
fn estimate_refuses_or_masks_non_finite_open_and_pinhole() {
    let f = Files::new();
    let base = f.estimate(&f.s("open.tiff"), &f.s("pinhole.tiff"), &f.s("clean"), &[]);
    assert!(base.status.success(), "{}", String::from_utf8_lossy(&base.stderr));
    let clean = kernels(&f.p("clean"));
    let at = [(40, 31), (41, 31), (60, 70)];
    for (role, file) in [("open", "open.tiff"), ("pinhole", "pinhole.tiff")] {
        for (what, v) in BAD {
            let bad = f.damaged(file, &format!("{role}-{what}.tiff"), v, &at);
            let (o, p) = if role == "open" { (bad.clone(), f.s("pinhole.tiff")) } else { (f.s("open.tiff"), bad.clone()) };
            let out = f.s(&format!("p-{role}-{what}"));
            let r = f.estimate(&o, &p, &out, &[]);
            let e = String::from_utf8_lossy(&r.stderr);
            assert_eq!(r.status.code(), Some(2), "{role} {what}: {e}");
            assert!(e.contains(&format!("{role}-{what}.tiff")) && e.contains("pixel (x=40, y=31) channel Y") && e.contains("3 non-finite"), "{role} {what}: {e}");
            assert!(!Path::new(&out).exists(), "nothing written on refusal");
            let r = f.estimate(&o, &p, &out, &["--mask-invalid"]);
            let e = String::from_utf8_lossy(&r.stderr);
            assert!(r.status.success(), "{role} {what}: {e}");
            assert!(e.contains("masked 3 non-finite sample(s)") && e.contains(&format!("{role}-{what}.tiff")), "{role} {what}: {e}");
            let got = kernels(Path::new(&out));
            assert!(got.iter().all(|v| v.is_finite()));
            let d = rel_l2(&got, &clean);
            assert!(d < 0.05, "{role} {what}: masked kernels differ from the clean run by {d:.3}");
        }
        // negative values: legal; a few pass silently, many are reported, both estimate
        let few = f.damaged(file, &format!("{role}-neg-few.tiff"), -0.01, &at);
        let (o, p) = if role == "open" { (few, f.s("pinhole.tiff")) } else { (f.s("open.tiff"), few) };
        let r = f.estimate(&o, &p, &f.s(&format!("n1-{role}")), &[]);
        assert!(r.status.success() && !String::from_utf8_lossy(&r.stderr).contains("negative"), "{}", String::from_utf8_lossy(&r.stderr));
        let many: Vec<(usize, usize)> = (0..W).flat_map(|x| (0..3).map(move |y| (x, y))).collect();
        let lots = f.damaged(file, &format!("{role}-neg-many.tiff"), -0.01, &many);
        let (o, p) = if role == "open" { (lots, f.s("pinhole.tiff")) } else { (f.s("open.tiff"), lots) };
        let r = f.estimate(&o, &p, &f.s(&format!("n2-{role}")), &[]);
        let e = String::from_utf8_lossy(&r.stderr);
        assert!(r.status.success(), "{e}");
        assert!(e.contains("288 of 9216 samples (3.1%) are negative, first at pixel (x=0, y=0) channel Y"), "{e}");
    }
}

#[test]
fn deblur_and_simulate_refuse_or_mask_non_finite_inputs() {
    let f = Files::new();
    // the true profile (a single tile), written by lensrig itself
    let g = truth();
    let source = lensrig::profile::SourceInfo {
        width: W,
        height: H,
        channels: vec!["Y".into()],
        sample_format: SampleFormat::F32,
        transfer: lensrig::image::Transfer::Linear,
        open: None,
        pinhole: None,
        black_level: vec![],
    };
    let table = lensrig::profile::PsfTable { kernel_size: 5, columns: 1, rows: 1, centers: g.centers.clone(), tile_size: None, files: Default::default() };
    lensrig::profile::Profile { meta: lensrig::profile::Profile::new_meta(source, vec![1.0], table), grid: g }.save(&f.p("profile")).unwrap();
    let profile = f.s("profile");
    let at = [(50, 50), (10, 80)];
    ok(&["deblur", "--profile", &profile, "--in", &f.s("open.tiff"), "--out", &f.s("clean.png"), "--quiet"]);
    let clean = lensrig::image::io::read_image(&f.p("clean.png")).unwrap();
    for (what, v) in BAD {
        let bad = f.damaged("open.tiff", &format!("photo-{what}.tiff"), v, &at);
        let out = f.s(&format!("out-{what}.png"));
        let e = refused(&["deblur", "--profile", &profile, "--in", &bad, "--out", &out, "--quiet"]);
        assert!(e.contains(&format!("photo-{what}.tiff")) && e.contains("pixel (x=50, y=50) channel Y"), "{e}");
        assert!(!Path::new(&out).exists());
        let e = ok(&["deblur", "--profile", &profile, "--in", &bad, "--out", &out, "--quiet", "--mask-invalid"]);
        assert!(e.contains("masked 2 non-finite sample(s)"), "{e}");
        let got = lensrig::image::io::read_image(Path::new(&out)).unwrap();
        // away from the masked pixels the restoration is the clean run's
        let (mut worst, mut sq, mut far) = (0.0f32, 0.0f64, 0usize);
        for y in 0..H {
            for x in 0..W {
                if at.iter().all(|&(ax, ay)| (x as isize - ax as isize).abs() > 8 || (y as isize - ay as isize).abs() > 8) {
                    let d = (got.planes[0].get(x, y) - clean.planes[0].get(x, y)).abs();
                    worst = worst.max(d);
                    sq += (d as f64).powi(2);
                    far += 1;
                }
            }
        }
        let rms = (sq / far as f64).sqrt();
        eprintln!("{what}: masked vs clean deblur away from the holes: rms {rms:.4}, max {worst:.4}");
        assert!(far > W * H / 2 && rms < 0.005 && worst < 0.05, "{what}: masked deblur differs from the clean one away from the holes: rms {rms:.4}, max {worst:.4}");
        // simulate: the sharp image has no data term; non-finite values are refused
        let sharp = f.damaged("pinhole.tiff", &format!("sharp-{what}.tiff"), v, &at);
        let e = refused(&["simulate", "--profile", &profile, "--sharp", &sharp, "--out", &f.s("pred.png")]);
        assert!(e.contains(&format!("sharp-{what}.tiff")) && e.contains("pixel (x=50, y=50) channel Y"), "{e}");
    }
    // negative values in the photo and the sharp image: legal; many are reported
    let many: Vec<(usize, usize)> = (0..W).flat_map(|x| (0..3).map(move |y| (x, y))).collect();
    let neg = f.damaged("open.tiff", "photo-neg.tiff", -0.01, &many);
    let e = ok(&["deblur", "--profile", &profile, "--in", &neg, "--out", &f.s("neg.png"), "--quiet"]);
    assert!(e.contains("are negative"), "{e}");
    let neg = f.damaged("pinhole.tiff", "sharp-neg.tiff", -0.01, &many);
    let e = ok(&["simulate", "--profile", &profile, "--sharp", &neg, "--out", &f.s("neg-pred.png")]);
    assert!(e.contains("are negative"), "{e}");
}

/// An 8-bit wide-open capture with a 16-bit pinhole: both are read onto one linear full scale
/// (the kernels match the float pair's within the 8-bit quantisation), and stderr says which
/// file's quantisation adds to its noise; a pair of one depth gets no such note.
#[test]
fn estimate_notes_a_pair_of_two_sample_depths() {
    let f = Files::new();
    let as_png = |from: &str, to: &str, bits: u8| {
        let img = lensrig::image::io::read_image(&f.p(from)).unwrap();
        let w = if bits == 8 { lensrig::image::io::write_png8 } else { lensrig::image::io::write_png16 };
        w(&f.p(to), &img, lensrig::fsutil::Overwrite::Never).unwrap();
        f.s(to)
    };
    let (o8, o16, p16) = (as_png("open.tiff", "open8.png", 8), as_png("open.tiff", "open16.png", 16), as_png("pinhole.tiff", "pinhole16.png", 16));
    let clean = f.estimate(&f.s("open.tiff"), &f.s("pinhole.tiff"), &f.s("clean"), &[]);
    assert!(clean.status.success(), "{}", String::from_utf8_lossy(&clean.stderr));
    let same = f.estimate(&o16, &p16, &f.s("same"), &[]);
    let e = String::from_utf8_lossy(&same.stderr);
    assert!(same.status.success() && !e.contains("quantisation"), "{e}");
    let mixed = f.estimate(&o8, &p16, &f.s("mixed"), &[]);
    let e = String::from_utf8_lossy(&mixed.stderr);
    assert!(mixed.status.success(), "{e}");
    assert!(e.contains("open8.png is 8-bit integer") && e.contains("pinhole16.png is 16-bit integer") && e.contains("open8.png's quantisation"), "{e}");
    let d = rel_l2(&kernels(&f.p("mixed")), &kernels(&f.p("clean")));
    assert!(d < 0.05, "the 8-bit/16-bit pair's kernels differ from the float pair's by {d:.3}");
}
