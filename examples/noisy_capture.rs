//! Benchmark helper (issue 12): `noise IN.png FULL_WELL_E READ_E SEED OUT.png` adds
//! Poisson–Gaussian sensor noise to a linear 16-bit PNG (values clipped to [0, 1]);
//! `psnr A.png B.png` prints the PSNR (dB) of B against A on the stored values.

use lensrig::fsutil::Overwrite;
use lensrig::image::io::{read_image, write_png16};
use std::path::Path;

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    match a.get(1).map(String::as_str) {
        Some("noise") if a.len() == 7 => {
            let mut img = read_image(Path::new(&a[2]))?;
            let (fw, rd, seed): (f64, f64, u64) = (a[3].parse()?, a[4].parse()?, a[5].parse()?);
            let mut rng = lensrig::rng::Rng::new(seed);
            for p in &mut img.planes {
                for v in p.data.iter_mut() {
                    *v = (((rng.poisson(v.max(0.0) as f64 * fw) + rd * rng.normal()) / fw) as f32).clamp(0.0, 1.0);
                }
            }
            write_png16(Path::new(&a[6]), &img, Overwrite::Replace)?;
        }
        Some("psnr") if a.len() == 4 => {
            let (x, y) = (read_image(Path::new(&a[2]))?, read_image(Path::new(&a[3]))?);
            let (mut se, mut n) = (0.0f64, 0usize);
            for (p, q) in x.planes.iter().zip(&y.planes) {
                for (u, v) in p.data.iter().zip(&q.data) {
                    se += ((u - v) as f64).powi(2);
                    n += 1;
                }
            }
            println!("{:.2}", 10.0 * (1.0 / (se / n.max(1) as f64)).log10());
        }
        _ => anyhow::bail!("usage: noisy_capture noise IN.png FULL_WELL_E READ_E SEED OUT.png | psnr A.png B.png"),
    }
    Ok(())
}
