//! What a perfect model's residual still holds under `pinhole_diffraction`, per channel: the
//! error of the best linear prediction of the wide-open capture from the stopped-down
//! reference, `E(f) = (P_O(f) − N_O)·φ(f)`, `φ = N_P / P_P(f)` (the reference's noise share per
//! frequency bin), on the central 256-px square, once with `P_P` from the noise-free reference
//! and once from the recorded one; beside it the truth floor's excess over the wide-open noise
//! (`proof::wiener_error_gain`), there and per tile of a 7×5 grid (÷ the wide-open noise).
//! docs/notes/diagnosis-history.md, "Session 32".
//! `cargo run --release --example refbias -- SEED W H K`
use lensrig::diagnose::proof::{render_case, CaseSpec};
use lensrig::image::Plane;
use lensrig::optics::capture::Sensor;
use lensrig::solve::fft::Fft2;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let n = |i: usize| a[i].parse::<usize>().unwrap();
    let (seed, w, h, k) = (n(1) as u64, n(2), n(3), n(4));
    let spec = CaseSpec { width: w, height: h, channels: 3, kernel_size: k, grid: (7, 5), ..CaseSpec::default() };
    let case = render_case(Some("pinhole_diffraction"), seed, &spec).unwrap();
    println!("seed {seed} {w}x{h} k {k}: truth {}", case.truth);
    let sensor = Sensor::default();
    let pin_scale = 1.0 / case.pinhole_frames as f64;
    let mean_in = |m: &Plane, x0: usize, y0: usize, x1: usize, y1: usize| {
        let mut s = 0.0;
        for y in y0..y1 {
            for x in x0..x1 {
                s += m.get(x, y) as f64;
            }
        }
        s / ((x1 - x0) * (y1 - y0)) as f64
    };
    let side = 256.min(w).min(h);
    let fft = Fft2::plan(side, side);
    let (x0, y0) = ((w - side) / 2, (h - side) / 2);
    // Hann-windowed power per bin, in variance units (white noise of variance v: v per bin)
    let power = |q: &Plane| {
        let mean = mean_in(q, x0, y0, x0 + side, y0 + side);
        let hann = |i: usize| 0.5 - 0.5 * (std::f64::consts::TAU * (i as f64 + 0.5) / side as f64).cos();
        let mut ws = 0.0;
        let buf: Vec<f32> = (0..side * side)
            .map(|i| {
                let wv = hann(i % side) * hann(i / side);
                ws += wv * wv;
                ((q.get(x0 + i % side, y0 + i / side) as f64 - mean) * wv) as f32
            })
            .collect();
        fft.forward(&buf).iter().map(|z| z.norm_sqr() as f64 / ws).collect::<Vec<f64>>()
    };
    for (c, name) in ["R", "G", "B"].iter().enumerate() {
        let p = &case.pinhole.image.planes[c];
        let var_ref = pin_scale * sensor.variance(p.mean() as f32) as f64;
        let (so, sc, sn) = (power(&case.open.image.planes[c]), power(&case.pinhole.clean[c]), power(p));
        let no = sensor.variance(case.open.image.planes[c].mean() as f32) as f64;
        let (mut e_clean, mut e_noisy, mut cnt) = (0.0, 0.0, 0.0);
        for i in 0..so.len() {
            let kx = i / side;
            let mult = if kx == 0 || kx == side / 2 { 1.0 } else { 2.0 };
            e_clean += mult * (so[i] - no) * var_ref / (sc[i] + var_ref);
            e_noisy += mult * (so[i] - no) * (var_ref / sn[i].max(1e-30)).min(1.0);
            cnt += mult;
        }
        let excess = Plane::from_fn(w, h, |x, y| case.true_variance[c].get(x, y) - case.open.variance[c].get(x, y));
        println!(
            "  {name}: central square: best prediction's error {:.3e} (noise-free reference's φ), {:.3e} (recorded); truth floor − open noise {:.3e}; open noise {no:.3e}",
            e_clean / cnt,
            e_noisy / cnt,
            mean_in(&excess, x0, y0, x0 + side, y0 + side)
        );
        for ty in 0..5 {
            let row: Vec<String> = (0..7)
                .map(|tx| {
                    let (xa, xb, ya, yb) = (tx * w / 7, (tx + 1) * w / 7, ty * h / 5, (ty + 1) * h / 5);
                    format!("{:.2}", mean_in(&excess, xa, ya, xb, yb) / mean_in(&case.open.variance[c], xa, ya, xb, yb))
                })
                .collect();
            println!("    tile row {ty}, truth excess ÷ open noise: {}", row.join(" "));
        }
    }
}
