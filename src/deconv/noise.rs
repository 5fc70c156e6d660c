//! Noise level of a captured channel, for defaults that need no tuning, and the use of a
//! stored noise law ([`crate::profile::noise::NoiseLaw`], `Var[x] = g x + r²` on the linear
//! axis) by `deblur`: where it comes from ([`NoiseSource`]), the channel level it implies, and
//! the check of a photograph against it.
//!
//! Donoho's robust estimator: the finest diagonal Haar detail `(a − b − c + d) / 2` of each
//! 2×2 block holds almost no signal in a blurred image, so its median absolute value divided
//! by 0.6745 estimates the standard deviation of white Gaussian noise. Values are on the
//! plane's own axis (call it on linear data for the solver).

use crate::image::Plane;
use crate::profile::noise::{haar_samples, NoiseLaw};

/// Where `deblur` takes the noise level from.
#[derive(Clone, Debug, Default, PartialEq)]
pub enum NoiseSource {
    /// The profile's stored law when it has one, else [`NoiseSource::Estimate`] (the library's
    /// [`super::deblur`] has no profile and estimates; [`super::capture::restore_file`]
    /// resolves this).
    #[default]
    Profile,
    /// Donoho's estimator on the photograph (white Gaussian noise assumed).
    Estimate,
    /// This law (`--noise gain=…,read=…` or a σ).
    Law(NoiseLaw),
}

impl std::str::FromStr for NoiseSource {
    type Err = crate::profile::noise::NoiseLawError;

    /// `profile`, `estimate`, a white-noise σ (`0.005`), or `gain=G,read=R` with one value for
    /// all channels or one per channel separated by `:` (`gain=6.7e-5:6.7e-5:7e-5,read=2.7e-4`),
    /// full-scale linear units.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        use crate::profile::noise::NoiseLawError::Invalid;
        let s = s.trim();
        match s {
            "profile" => return Ok(Self::Profile),
            "estimate" => return Ok(Self::Estimate),
            _ => {}
        }
        let list = |v: &str| -> Result<Vec<f64>, Self::Err> { v.split(':').map(|x| x.trim().parse::<f64>().map_err(|_| Invalid(format!("'{x}' is not a number")))).collect() };
        let law = if let Ok(sigma) = s.parse::<f64>() {
            NoiseLaw::white(sigma, 1)
        } else {
            let (mut gain, mut read) = (None, None);
            for part in s.split(',') {
                match part.split_once('=') {
                    Some(("gain", v)) => gain = Some(list(v)?),
                    Some(("read", v)) => read = Some(list(v)?),
                    _ => return Err(Invalid(format!("'{part}': expected gain=…, read=…, a σ, 'profile' or 'estimate'"))),
                }
            }
            let (gain, read) = (gain.unwrap_or_else(|| vec![0.0]), read.unwrap_or_else(|| vec![0.0]));
            let n = gain.len().max(read.len());
            let spread = |v: Vec<f64>| if v.len() == 1 { vec![v[0]; n] } else { v };
            NoiseLaw::new(spread(gain), spread(read), "given")
        };
        law.check()?;
        Ok(Self::Law(law))
    }
}

/// The disagreement (either way) between the photograph's own noise estimate and the law
/// beyond which `deblur` warns.
pub const LAW_DISAGREEMENT: f32 = 2.0;

/// The noise standard deviation the law gives channel `c` of `p` on average:
/// `√(g · mean(x) + r²)` (the root mean variance over the pixels).
pub fn law_sigma(law: &NoiseLaw, c: usize, p: &[f32]) -> f32 {
    let mean = p.iter().map(|v| v.max(0.0) as f64).sum::<f64>() / p.len().max(1) as f64;
    law.variance(c, mean as f32).sqrt()
}

/// What Donoho's estimator should read on `p` if its noise follows `law`: the median over the
/// 2×2 blocks of the law's `σ` at the block mean (the estimator is a median of block details).
pub fn expected_estimate(law: &NoiseLaw, c: usize, p: &Plane) -> f32 {
    let mut s: Vec<f32> = haar_samples(p, f32::INFINITY).iter().map(|(m, _)| law.variance(c, *m).sqrt()).collect();
    if s.is_empty() {
        return 0.0;
    }
    let mid = s.len() / 2;
    let (_, m, _) = s.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    *m
}

/// Checks the photograph's own noise estimate (`estimated[c]`, Donoho) against the law; one
/// warning per channel where they differ by more than [`LAW_DISAGREEMENT`]×.
pub fn check_law(law: &NoiseLaw, planes: &[Plane], estimated: &[f32], names: &[String]) -> Vec<String> {
    let mut out = Vec::new();
    for (c, (p, est)) in planes.iter().zip(estimated).enumerate() {
        let want = expected_estimate(law, c, p);
        let ratio = if want > 0.0 { est / want } else { f32::INFINITY };
        if !(1.0 / LAW_DISAGREEMENT..=LAW_DISAGREEMENT).contains(&ratio) {
            let name = names.get(c).map_or("?", |s| s.as_str());
            out.push(format!(
                "channel {name}: the photograph's own noise estimate σ = {est:.2e} is {ratio:.2}× what the noise law predicts ({want:.2e}); taken at another ISO or exposure? give --noise"
            ));
        }
    }
    out
}

/// The estimated noise standard deviation of `p` (0 for planes smaller than 2×2).
pub fn estimate_sigma(p: &Plane) -> f32 {
    let mut d = Vec::with_capacity((p.width / 2) * (p.height / 2));
    for y in (0..p.height.saturating_sub(1)).step_by(2) {
        for x in (0..p.width.saturating_sub(1)).step_by(2) {
            let v = (p.get(x, y) - p.get(x + 1, y) - p.get(x, y + 1) + p.get(x + 1, y + 1)) * 0.5;
            d.push(v.abs());
        }
    }
    if d.is_empty() {
        return 0.0;
    }
    let mid = d.len() / 2;
    let (_, m, _) = d.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    *m / 0.6745
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_noise_level_on_a_smooth_image() {
        let mut s = 99u64;
        let mut gauss = || {
            // Box–Muller from an LCG
            let mut u = || {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            let (a, b) = (u(), u());
            ((-2.0 * a.ln()).sqrt() * (2.0 * std::f64::consts::PI * b).cos()) as f32
        };
        let p = Plane::from_fn(128, 128, |x, y| 0.3 + 0.2 * ((x as f32) * 0.05).sin() * ((y as f32) * 0.03).cos() + 0.01 * gauss());
        let s = estimate_sigma(&p);
        assert!((s - 0.01).abs() < 0.001, "{s}");
        assert_eq!(estimate_sigma(&Plane::filled(1, 5, 1.0)), 0.0);
    }

    #[test]
    fn noise_option_parses() {
        assert_eq!("profile".parse::<NoiseSource>().unwrap(), NoiseSource::Profile);
        assert_eq!("estimate".parse::<NoiseSource>().unwrap(), NoiseSource::Estimate);
        assert_eq!("0.005".parse::<NoiseSource>().unwrap(), NoiseSource::Law(NoiseLaw::white(0.005, 1)));
        let NoiseSource::Law(l) = "gain=1e-4:2e-4:3e-4,read=2e-4".parse::<NoiseSource>().unwrap() else { panic!() };
        assert_eq!((l.gain, l.read), (vec![1e-4, 2e-4, 3e-4], vec![2e-4; 3]));
        assert!("gain=1e-4:2e-4,read=1:2:3".parse::<NoiseSource>().is_err());
        assert!("gain=-1".parse::<NoiseSource>().is_err());
        assert!("loud".parse::<NoiseSource>().is_err());
    }

    #[test]
    fn a_photo_is_checked_against_the_law() {
        let mut rng = crate::rng::Rng::new(4);
        let fw = 15_000.0;
        let p = Plane::from_fn(256, 128, |x, _| {
            let v = 0.05 + 0.8 * x as f64 / 256.0;
            ((rng.poisson(v * fw) + 4.0 * rng.normal()) / fw) as f32
        });
        let names = vec!["G".to_string()];
        let est = [estimate_sigma(&p)];
        let law = NoiseLaw::new(vec![1.0 / fw], vec![4.0 / fw], "given");
        assert!(check_law(&law, std::slice::from_ref(&p), &est, &names).is_empty());
        // the same photo against a law for 4× the full well (half the σ at this level) and 9×
        let quiet = NoiseLaw::new(vec![1.0 / (9.0 * fw)], vec![4.0 / fw], "given");
        let w = check_law(&quiet, std::slice::from_ref(&p), &est, &names);
        assert!(w.len() == 1 && w[0].contains("channel G"), "{w:?}");
        assert!(check_law(&NoiseLaw::new(vec![1.0 / (2.0 * fw)], vec![4.0 / fw], "given"), std::slice::from_ref(&p), &est, &names).is_empty());
    }
}
