//! Where a test-bed lens's kernel error sits (issue 16, branch e15a): bias against variance over
//! noise seeds, by zone of the disc, by tile, and what the grid and the support can represent.
//!
//! `cargo run --release --example errsplit -- /work/shared/data/lenses/lac9-singlet-stop-behind-f6.3 [seeds…]`
//!
//! Renders the test bed's pair (`lensrig bench --testbed`'s rendering, seed `s`) for each seed
//! (default 1 4 5), estimates with the default settings for the first seed and with its kernel
//! size, grid and field variation fixed for the others, and prints per channel, over the
//! kernels (medians): the RMS error over seeds, the bias `√(‖ē‖² − var/n)` and the spread, and
//! the shares of bias and variance energy in the zones of the truth's 99 % radius `R` (core
//! `r ≤ R/4`, body `R/4–3R/4`, edge `3R/4–5R/4`, floor beyond); the first seed's error per
//! tile; the centre tile's ring means of truth and bias; the truth's energy outside the
//! estimate's support; and the error of the truth's own field resampled at the estimate's
//! centres (and at finer grids) and blended, against the truth at every pixel of a dense grid.

use lensrig::estimate::testbed::{embed_centered, noise_target_pair, relative_error_centered};
use lensrig::estimate::{estimate, support_radius, tile_for_grid, EstimateOptions};
use lensrig::image::{Plane, Transfer};
use lensrig::optics::capture::{Rendered, Sensor};
use lensrig::optics::psf_grid::PsfGrid;
use lensrig::profile::Profile;

const SENSOR: Sensor = Sensor { full_well_e: 15_000.0, read_noise_e: 4.0, bits: 16, transfer: Transfer::Linear, noise: true };

fn pair(truth: &PsfGrid, w: usize, h: usize, seed: u64) -> (Rendered, Rendered) {
    noise_target_pair(truth, w, h, seed, &SENSOR, 0.75).unwrap()
}

fn med(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn norm2(p: &Plane) -> f64 {
    p.data.iter().map(|&v| (v as f64).powi(2)).sum()
}

/// Zone of pixel `(x, y)` of an `n × n` kernel against the radius `r99`: 0 core … 3 floor.
fn zone(x: usize, y: usize, n: usize, r99: f64) -> usize {
    let c = (n / 2) as f64;
    let r = ((x as f64 - c).powi(2) + (y as f64 - c).powi(2)).sqrt();
    if r <= r99 / 4.0 {
        0
    } else if r <= 0.75 * r99 {
        1
    } else if r <= 1.25 * r99 {
        2
    } else {
        3
    }
}

/// The truth's 99 % radius (Euclidean, about the kernel centre, raw encircled energy).
fn r99(p: &Plane) -> f64 {
    let c = (p.width / 2) as f64;
    let mut v: Vec<(f64, f64)> = (0..p.height).flat_map(|y| (0..p.width).map(move |x| (x, y))).map(|(x, y)| (((x as f64 - c).powi(2) + (y as f64 - c).powi(2)).sqrt(), p.get(x, y) as f64)).collect();
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    let total: f64 = v.iter().map(|q| q.1).sum();
    let mut acc = 0.0;
    for (r, e) in v {
        acc += e;
        if acc >= 0.99 * total {
            return r;
        }
    }
    c
}

fn grid_representation(truth: &PsfGrid, w: usize, h: usize, cols: usize, rows: usize) -> Vec<(f64, f64)> {
    let centers = PsfGrid::regular_centers(w, h, cols, rows);
    (0..truth.channels.len())
        .map(|c| {
            let kernels: Vec<Vec<Plane>> = (0..truth.channels.len()).map(|cc| centers.iter().map(|&[x, y]| truth.kernel_at(cc, x, y)).collect()).collect();
            let g = PsfGrid { kernel_size: truth.kernel_size, columns: cols, rows, centers: centers.clone(), channels: truth.channels.clone(), kernels };
            let mut e: Vec<f64> = Vec::new();
            for j in 0..15 {
                for i in 0..20 {
                    let (x, y) = ((i as f64 + 0.5) * w as f64 / 20.0, (j as f64 + 0.5) * h as f64 / 15.0);
                    e.push(relative_error_centered(&g.kernel_at(c, x, y), &truth.kernel_at(c, x, y)));
                }
            }
            let m = med(&mut e);
            (m, e[e.len() - 1])
        })
        .collect()
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let dir = std::path::PathBuf::from(&args[1]);
    let seeds: Vec<u64> = if args.len() > 2 { args[2..].iter().map(|s| s.parse().unwrap()).collect() } else { vec![1, 4, 5] };
    let truth = Profile::load(&dir).unwrap();
    let (w, h) = (truth.meta.source.width, truth.meta.source.height);
    let tg = truth.grid;
    let mut ests: Vec<PsfGrid> = Vec::new();
    let mut opts = EstimateOptions::default();
    if let Some(j) = std::env::var("ERRSPLIT_JOINT").ok().and_then(|v| v.parse().ok()) {
        opts.joint_iterations = j;
    }
    for &s in &seeds {
        let (open, pin) = pair(&tg, w, h, s);
        let e = estimate(&open.image, &pin.image, &opts).unwrap();
        let g = e.profile.grid.clone();
        let cpu: Vec<String> = e.stage_seconds.iter().map(|t| format!("{} {:.1}", t.stage, t.cpu.unwrap_or(f64::NAN))).collect();
        eprintln!("seed {s}: {}×{} of {} px; CPU-s {}", g.columns, g.rows, g.kernel_size, cpu.join(", "));
        if ests.is_empty() {
            opts.kernel_size = Some(g.kernel_size);
            opts.tile = tile_for_grid(w, h, g.columns, g.rows);
            opts.field_variation = Some(e.field_variation.clone());
        }
        ests.push(g);
    }
    let g0 = &ests[0];
    let n = g0.kernel_size.max(tg.kernel_size);
    let ns = seeds.len() as f64;
    println!("| channel | R99 truth (px) | RMS err | bias | std | bias core/body/edge/floor | var core/body/edge/floor | seed-1 err | mean-of-seeds err |");
    for c in 0..tg.channels.len() {
        let (mut rms, mut bias, mut std, mut e1, mut em) = (vec![], vec![], vec![], vec![], vec![]);
        let (mut bz, mut vz) = ([0.0f64; 4], [0.0f64; 4]);
        let mut rr = vec![];
        for t in 0..g0.tile_count() {
            let [x, y] = g0.centers[t];
            let tr = embed_centered(&tg.kernel_at(c, x, y), n);
            let t2 = norm2(&tr);
            let r = r99(&tr);
            rr.push(r);
            let errs: Vec<Plane> = ests
                .iter()
                .map(|g| {
                    let mut d = embed_centered(&g.kernels[c][t], n);
                    d.data.iter_mut().zip(&tr.data).for_each(|(a, b)| *a -= b);
                    d
                })
                .collect();
            let mut mean = Plane::new(n, n);
            errs.iter().for_each(|d| mean.data.iter_mut().zip(&d.data).for_each(|(m, v)| *m += v / ns as f32));
            let mut var = Plane::new(n, n);
            errs.iter().for_each(|d| var.data.iter_mut().zip(d.data.iter().zip(&mean.data)).for_each(|(v, (a, m))| *v += (a - m).powi(2) / (ns as f32 - 1.0).max(1.0)));
            let (vs, ms): (f64, f64) = (var.data.iter().map(|&v| v as f64).sum(), norm2(&mean));
            rms.push((errs.iter().map(norm2).sum::<f64>() / ns / t2).sqrt());
            let b2 = (ms - vs / ns).max(0.0);
            bias.push((b2 / t2).sqrt());
            std.push((vs / t2).sqrt());
            e1.push((norm2(&errs[0]) / t2).sqrt());
            em.push((ms / t2).sqrt());
            for yy in 0..n {
                for xx in 0..n {
                    let z = zone(xx, yy, n, r);
                    bz[z] += (mean.get(xx, yy) as f64).powi(2);
                    vz[z] += var.get(xx, yy) as f64;
                }
            }
        }
        let (bt, vt): (f64, f64) = (bz.iter().sum(), vz.iter().sum());
        let f = |z: &[f64; 4], t: f64| z.iter().map(|v| format!("{:.2}", v / t)).collect::<Vec<_>>().join("/");
        println!(
            "| {} | {:.1} | {:.2}% | {:.2}% | {:.2}% | {} | {} | {:.2}% | {:.2}% |",
            tg.channels[c],
            med(&mut rr),
            100.0 * med(&mut rms),
            100.0 * med(&mut bias),
            100.0 * med(&mut std),
            f(&bz, bt),
            f(&vz, vt),
            100.0 * med(&mut e1.clone()),
            100.0 * med(&mut em)
        );
        let row: Vec<String> = e1.iter().map(|e| format!("{:.1}", 100.0 * e)).collect();
        println!("    seed-1 per tile ({}×{}, row-major): {}", g0.columns, g0.rows, row.join(" "));
    }
    // ring means in the centre-most tile
    let tc = (g0.rows / 2) * g0.columns + g0.columns / 2;
    let [x, y] = g0.centers[tc];
    for c in 0..tg.channels.len() {
        let tr = embed_centered(&tg.kernel_at(c, x, y), n);
        let mut mean = Plane::new(n, n);
        for g in &ests {
            let e = embed_centered(&g.kernels[c][tc], n);
            mean.data.iter_mut().zip(e.data.iter().zip(&tr.data)).for_each(|(m, (a, b))| *m += (a - b) / ns as f32);
        }
        let cc = (n / 2) as f64;
        let rmax = n / 2;
        let (mut ts, mut bs, mut cnt) = (vec![0.0f64; rmax + 1], vec![0.0f64; rmax + 1], vec![0usize; rmax + 1]);
        for yy in 0..n {
            for xx in 0..n {
                let r = (((xx as f64 - cc).powi(2) + (yy as f64 - cc).powi(2)).sqrt().round() as usize).min(rmax);
                ts[r] += tr.get(xx, yy) as f64;
                bs[r] += mean.get(xx, yy) as f64;
                cnt[r] += 1;
            }
        }
        let step = if rmax > 30 { 2 } else { 1 };
        let row: Vec<String> = (0..=rmax).step_by(step).map(|r| format!("{r}:{:.2e}/{:+.1e}", ts[r] / cnt[r] as f64, bs[r] / cnt[r] as f64)).collect();
        println!("ring means {} tile {tc} (r: truth/bias): {}", tg.channels[c], row.join(" "));
    }
    // the central 7×7 of truth and mean estimate, and the bias energy within r ≤ 1, 2, 4
    for c in 0..tg.channels.len() {
        let tr = embed_centered(&tg.kernel_at(c, x, y), n);
        let mut mean = Plane::new(n, n);
        for g in &ests {
            let e = embed_centered(&g.kernels[c][tc], n);
            mean.data.iter_mut().zip(&e.data).for_each(|(m, a)| *m += a / ns as f32);
        }
        let h = n / 2;
        println!("centre 7×7 {} tile {tc}: truth | mean estimate (×1e4)", tg.channels[c]);
        for yy in h - 3..=h + 3 {
            let a: Vec<String> = (h - 3..=h + 3).map(|xx| format!("{:5.2}", 1e4 * tr.get(xx, yy))).collect();
            let b: Vec<String> = (h - 3..=h + 3).map(|xx| format!("{:5.2}", 1e4 * mean.get(xx, yy))).collect();
            println!("    {} | {}", a.join(" "), b.join(" "));
        }
        let t2 = norm2(&tr);
        let within = |rad: f64| -> f64 {
            let mut s = 0.0;
            for yy in 0..n {
                for xx in 0..n {
                    if ((xx as f64 - h as f64).powi(2) + (yy as f64 - h as f64).powi(2)).sqrt() <= rad {
                        s += ((mean.get(xx, yy) - tr.get(xx, yy)) as f64).powi(2);
                    }
                }
            }
            s
        };
        let tot = within(1e9);
        println!("    mean-estimate error {:.2}%; share of its energy within r ≤ 1 / 2 / 4 / 8: {:.2} / {:.2} / {:.2} / {:.2}", 100.0 * (tot / t2).sqrt(), within(1.0) / tot, within(2.0) / tot, within(4.0) / tot, within(8.0) / tot);
    }
    // support: truth energy outside the estimate's box, the estimate's outside the truth's
    for c in 0..tg.channels.len() {
        let mut outside = vec![];
        for t in 0..g0.tile_count() {
            let [x, y] = g0.centers[t];
            let tr = tg.kernel_at(c, x, y);
            let inside = embed_centered(&embed_centered(&tr, g0.kernel_size.min(tr.width)), tr.width);
            outside.push(1.0 - inside.sum() / tr.sum());
        }
        let sp: Vec<f64> = g0.kernels[c].iter().map(|k| support_radius(k, 0.99)).collect();
        println!("support {}: truth energy outside the {}-px estimate: max {:.2e}; estimate's floor-subtracted r99 (Chebyshev) median {:.0}", tg.channels[c], g0.kernel_size, outside.iter().copied().fold(0.0, f64::max), med(&mut sp.clone()));
    }
    // grid representation
    for (cols, rows) in [(g0.columns, g0.rows), (6, 4), (8, 6), (tg.columns, tg.rows)] {
        let rep = grid_representation(&tg, w, h, cols, rows);
        let s: Vec<String> = rep.iter().zip(&tg.channels).map(|((m, x), ch)| format!("{ch} {:.2}%/{:.2}%", 100.0 * m, 100.0 * x)).collect();
        println!("truth resampled at {cols}×{rows} and blended, vs truth on a 20×15 grid (median/max): {}", s.join(", "));
    }
    // field variation of the truth: corners against centre
    for c in 0..tg.channels.len() {
        let cen = tg.kernel_at(c, w as f64 / 2.0 - 0.5, h as f64 / 2.0 - 0.5);
        let cor = tg.kernel_at(c, 0.0, 0.0);
        let d = ((w as f64 / 2.0).powi(2) + (h as f64 / 2.0).powi(2)).sqrt();
        println!("truth {}: centre→corner relative change {:.2}% ({:.2e}/px)", tg.channels[c], 100.0 * relative_error_centered(&cor, &cen), relative_error_centered(&cor, &cen) / d);
    }
}
