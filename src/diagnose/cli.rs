//! `lensrig diagnose`: arguments and the command. Also a hidden benchmark mode
//! (`--bench-seeds N`) that renders the proof suite ([`super::proof`]) and prints the table
//! (effect, named, base χ², final χ², floor ratio) instead of reading files.

use super::proof::{floor_ratio, render_case, CaseSpec, CONCEALED};
use super::report::{write_report, Sources};
use super::noise::NoiseCurve;
use super::{diagnose, DiagnoseOptions};
use crate::estimate::EstimateOptions;
use crate::image::io::read_pair;
use crate::image::Transfer;
use crate::profile::Profile;
use anyhow::{bail, Context, Result};
use std::path::PathBuf;

#[derive(clap::Args, Debug, Clone)]
pub struct DiagnoseArgs {
    /// Wide-open capture (PNG/TIFF).
    #[arg(long, required_unless_present_any = ["bench_seeds", "session"], conflicts_with = "session")]
    pub open: Option<PathBuf>,
    /// Pinhole-aperture capture of the same target.
    #[arg(long, required_unless_present_any = ["bench_seeds", "session"], conflicts_with = "session")]
    pub pinhole: Option<PathBuf>,
    /// A capture session (from `lensrig capture`): every finished pair is diagnosed into
    /// `OUT/<pair key>/`, with the transfer curve, dark level and frame counts from its metadata.
    #[arg(long)]
    pub session: Option<PathBuf>,
    /// Frames averaged in the wide-open and the pinhole capture (`--frames 1,16`): the
    /// reference's noise relative to the wide-open capture's. A session's metadata gives them.
    #[arg(long, value_delimiter = ',', num_args = 2)]
    pub frames: Option<Vec<usize>>,
    /// Profile to diagnose; default: estimate a base profile from the pair.
    #[arg(long)]
    pub profile: Option<PathBuf>,
    /// Report directory (created; files in it are replaced).
    #[arg(long, required_unless_present = "bench_seeds")]
    pub out: Option<PathBuf>,
    /// How the files are declared to encode light (the diagnosis may find otherwise).
    #[arg(long, default_value = "linear")]
    pub transfer: Transfer,
    /// Kernel size for the base estimate (odd); default: measured.
    #[arg(long)]
    pub kernel: Option<usize>,
    /// Tile side for the base estimate.
    #[arg(long)]
    pub tile: Option<usize>,
    /// Iterations of the base estimate.
    #[arg(long, default_value_t = 150)]
    pub max_iterations: usize,
    /// At most this many effects are added.
    #[arg(long, default_value_t = 4)]
    pub max_effects: usize,
    /// Benchmark: run the proof suite over this many seeds and print the table.
    #[arg(long, hide = true)]
    pub bench_seeds: Option<u64>,
    /// Benchmark: first seed.
    #[arg(long, hide = true, default_value_t = 1)]
    pub bench_first_seed: u64,
    /// Benchmark: only this effect (or "clean").
    #[arg(long, hide = true)]
    pub bench_effect: Option<String>,
    /// No progress output.
    #[arg(long)]
    pub quiet: bool,
}

fn options(a: &DiagnoseArgs) -> DiagnoseOptions {
    DiagnoseOptions {
        estimate: EstimateOptions { kernel_size: a.kernel, tile: a.tile, max_iterations: a.max_iterations, joint_iterations: 0, ..Default::default() },
        max_effects: a.max_effects,
        progress: !a.quiet,
        ..Default::default()
    }
}

/// Runs `lensrig diagnose`.
///
/// # Errors
/// Unreadable inputs or profile, a failed diagnosis, or an unwritable report directory, each
/// naming the file.
pub fn run(a: &DiagnoseArgs) -> Result<()> {
    if let Some(n) = a.bench_seeds {
        return bench(a, n);
    }
    if let (Some(session), Some(out)) = (&a.session, &a.out) {
        return run_session(a, session, out);
    }
    let (Some(open), Some(pinhole), Some(out)) = (&a.open, &a.pinhole, &a.out) else {
        bail!("--open, --pinhole and --out are required (or --session and --out)");
    };
    if let Some(k) = a.kernel {
        if k % 2 == 0 || k < 3 {
            bail!("--kernel must be odd and at least 3, got {k}");
        }
    }
    let (mut o, mut p) = read_pair(open, pinhole)?;
    o.transfer = a.transfer;
    p.transfer = a.transfer;
    let profile = match &a.profile {
        Some(dir) => Some(Profile::load(dir)?),
        None => None,
    };
    let mut opts = options(a);
    if let Some(f) = &a.frames {
        if f.len() != 2 || f.contains(&0) {
            bail!("--frames takes two positive counts, wide-open then pinhole, e.g. --frames 1,16");
        }
        opts.pinhole_variance_scale = f[0] as f64 / f[1] as f64;
    }
    diagnose_files(&o, &p, profile.as_ref(), &opts, open, pinhole, a.profile.as_deref(), out)
}

#[allow(clippy::too_many_arguments)]
fn diagnose_files(o: &crate::image::Image, p: &crate::image::Image, profile: Option<&Profile>, opts: &DiagnoseOptions, open: &std::path::Path, pinhole: &std::path::Path, profile_dir: Option<&std::path::Path>, out: &std::path::Path) -> Result<()> {
    let d = diagnose(o, p, profile, opts).with_context(|| format!("diagnosing {} against {}", open.display(), pinhole.display()))?;
    let src = Sources { open: open.display().to_string(), pinhole: pinhole.display().to_string(), profile: profile_dir.map(|p| p.display().to_string()) };
    write_report(&d, out, &src)?;
    let names: Vec<&str> = d.effects.iter().map(|e| e.name.as_str()).collect();
    println!(
        "{}; reduced χ² {:.3} → {:.3}; effects: {}; report: {}",
        d.verdict,
        d.base.reduced_chi2(),
        d.final_fit.reduced_chi2(),
        if names.is_empty() { "none".to_string() } else { names.join(", ") },
        out.join("index.html").display()
    );
    Ok(())
}

/// `--session`: every finished pair of a capture session, each into `out/<pair key>/`. The
/// transfer curve and the frame counts come from the frames' sidecars; a dark frame's mean is
/// subtracted from both captures (linear data only) so that the sensor's own black level is
/// not reported as a mismatch.
fn run_session(a: &DiagnoseArgs, session: &std::path::Path, out: &std::path::Path) -> Result<()> {
    use crate::rig::session::{load_frame_record, load_session};
    let rec = load_session(session)?;
    if rec.pairs.is_empty() {
        bail!("session {} has no finished pairs (status: {})", session.display(), rec.status);
    }
    for pair in &rec.pairs {
        let pd = session.join(&pair.dir);
        let (open_p, pin_p) = (pd.join(&pair.open), pd.join(&pair.pinhole));
        let (mut o, mut p) = read_pair(&open_p, &pin_p)?;
        let om = load_frame_record(&pd.join("open.toml"))?;
        let pm = load_frame_record(&pd.join("pinhole.toml"))?;
        let transfer: Transfer = om.transfer.parse().map_err(|e| anyhow::anyhow!("{}: transfer: {e}", pd.join("open.toml").display()))?;
        o.transfer = transfer;
        p.transfer = transfer;
        let mut dark_levels: Vec<f32> = Vec::new();
        if let (Some(dark), Transfer::Linear) = (&pair.dark, transfer) {
            let d = crate::image::io::read_image(&pd.join(dark))?;
            dark_levels = (0..o.channel_count()).map(|c| d.planes.get(c).or(d.planes.first()).map_or(0.0, |q| q.mean() as f32)).collect();
            for img in [&mut o, &mut p] {
                for (c, plane) in img.planes.iter_mut().enumerate() {
                    let level = dark_levels.get(c).copied().unwrap_or(0.0);
                    plane.data.iter_mut().for_each(|v| *v = (*v - level).max(0.0));
                }
            }
        }
        let mut opts = options(a);
        opts.pinhole_variance_scale = om.frames_averaged.max(1) as f64 / pm.frames_averaged.max(1) as f64;
        // the temporal noise of one frame, over the averaged frames: the average's variance is
        // that over the frame count; a dark level subtracted above shifts the levels
        if let Some(t) = &om.temporal_noise {
            let shift = if transfer == Transfer::Linear { dark_levels.clone() } else { vec![0.0; t.len()] };
            let n = om.frames_averaged.max(1) as f64;
            opts.repeat_noise = Some(
                t.iter()
                    .enumerate()
                    .map(|(c, rows)| {
                        let d = shift.get(c).or(shift.first()).copied().unwrap_or(0.0) as f64;
                        NoiseCurve { bins: rows.iter().map(|r| ((r[0] - d).max(0.0), r[1] / n, r[2] as usize)).collect() }
                    })
                    .collect(),
            );
        }
        let dir = out.join(&pair.key);
        if !a.quiet {
            eprintln!(
                "diagnosing pair {} (stage {} mm; {} / {} frames averaged; noise model from {})",
                pair.key,
                pair.stage_mm,
                om.frames_averaged,
                pm.frames_averaged,
                if opts.repeat_noise.is_some() { "the repeated frames" } else { "the residual" }
            );
        }
        diagnose_files(&o, &p, None, &opts, &open_p, &pin_p, None, &dir).with_context(|| format!("pair {}", pair.key))?;
    }
    Ok(())
}

/// One row of the benchmark table.
#[derive(Clone, Debug, serde::Serialize)]
pub struct BenchRow {
    pub effect: String,
    pub seed: u64,
    pub named: String,
    pub correct: bool,
    pub base_chi2: f64,
    pub final_chi2: f64,
    pub floor_ratio: f64,
    /// The first effect's parameters against the rendered truth, for the keys both have
    /// (`key fitted/true`; empty when the effect is misnamed or has no numeric truth).
    pub recovered: String,
    pub seconds: f64,
}

/// `key fitted/true` for every numeric key of `truth` that `fitted` also has (arrays: the first
/// element, the first channel).
pub fn recovered_text(fitted: &serde_json::Value, truth: &serde_json::Value) -> String {
    let num = |v: &serde_json::Value| v.as_f64().or_else(|| v.as_array().and_then(|a| a.first()).and_then(serde_json::Value::as_f64));
    let Some(t) = truth.as_object() else { return String::new() };
    t.iter()
        .filter_map(|(k, tv)| Some(format!("{k} {}/{}", short(num(&fitted[k.as_str()])?), short(num(tv)?))))
        .collect::<Vec<_>>()
        .join(", ")
}

fn short(v: f64) -> String {
    if v == 0.0 {
        "0".into()
    } else if v.abs() >= 10.0 {
        format!("{v:.1}")
    } else {
        let digits = (2 - v.abs().log10().floor() as i32).clamp(0, 6) as usize;
        format!("{v:.digits$}")
    }
}

/// Diagnoses one proof case and scores it against the truth.
///
/// # Errors
/// An unknown effect or a failed diagnosis.
pub fn bench_case(effect: Option<&str>, seed: u64, spec: &CaseSpec, opts: &DiagnoseOptions) -> Result<(BenchRow, super::Diagnosis, super::proof::Case)> {
    let t = std::time::Instant::now();
    let case = render_case(effect, seed, spec).map_err(anyhow::Error::msg)?;
    let opts = DiagnoseOptions { pinhole_variance_scale: 1.0 / case.pinhole_frames as f64, ..opts.clone() };
    let d = diagnose(&case.open.image, &case.pinhole.image, None, &opts)?;
    let named = d.effects.first().map_or("no mismatch".to_string(), |e| e.name.clone());
    let correct = match effect {
        Some(e) => named == e,
        None => d.effects.is_empty(),
    };
    let ratio = floor_ratio(&case, &d.final_fit.predicted, &d.final_fit.eval);
    let recovered = match (correct, d.effects.first()) {
        (true, Some(e)) => recovered_text(&e.parameters, &case.truth),
        _ => String::new(),
    };
    let row = BenchRow {
        effect: effect.unwrap_or("clean").to_string(),
        seed,
        named,
        correct,
        base_chi2: d.base.reduced_chi2(),
        final_chi2: d.final_fit.reduced_chi2(),
        floor_ratio: ratio,
        recovered,
        seconds: t.elapsed().as_secs_f64(),
    };
    Ok((row, d, case))
}

/// Options the proof suite uses (small kernels, few iterations).
pub fn proof_options(spec: &CaseSpec) -> DiagnoseOptions {
    DiagnoseOptions { estimate: EstimateOptions { kernel_size: Some(spec.kernel_size), tile: Some(96), max_iterations: 150, joint_iterations: 0, ..Default::default() }, ..Default::default() }
}

fn bench(a: &DiagnoseArgs, seeds: u64) -> Result<()> {
    let spec = CaseSpec::default();
    let opts = proof_options(&spec);
    let effects: Vec<Option<&str>> = match a.bench_effect.as_deref() {
        Some("clean") => vec![None],
        Some(e) => vec![Some(e)],
        None => std::iter::once(None).chain(CONCEALED.iter().map(|e| Some(*e))).collect(),
    };
    println!("{:<22} {:>4} {:<22} {:>3} {:>10} {:>10} {:>8} {:>6}  fitted/true", "effect", "seed", "named first", "ok", "base χ²", "final χ²", "floor×", "s");
    let (mut ok, mut total) = (0, 0);
    for e in effects {
        for seed in a.bench_first_seed..a.bench_first_seed + seeds {
            let (r, d, _c) = bench_case(e, seed, &spec, &opts)?;
            if a.bench_effect.is_some() {
                eprintln!("truth {}", _c.truth);
                for n in &d.noise {
                    eprintln!("noise {}: a {:.3e} b {:.3e} misfit {:.3} | linear law misfit {:.3}; bins {:?}", n.channel, n.a, n.b, n.misfit, n.misfit_linear, n.curve.bins);
                }
                let sp = |a: &super::analysis::Analysis| a.spectrum.iter().map(|(f, p)| format!("{f:.2}:{p:.2}")).collect::<Vec<_>>().join(" ");
                eprintln!("residual spectrum, base:  {}", sp(&d.base_analysis));
                eprintln!("residual spectrum, final: {}", sp(&d.final_analysis));
                for r in &d.rounds {
                    for c in r {
                        eprintln!("  {} {:.4} {:.1} {} {}", c.name, c.reduced_chi2, c.delta_bic, c.note, c.parameters);
                    }
                }
            }
            total += 1;
            ok += r.correct as usize;
            println!("{:<22} {:>4} {:<22} {:>3} {:>10.3} {:>10.3} {:>8.3} {:>6.1}  {}", r.effect, r.seed, r.named, if r.correct { "yes" } else { "NO" }, r.base_chi2, r.final_chi2, r.floor_ratio, r.seconds, r.recovered);
        }
    }
    println!("{ok} of {total} cases named correctly");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::recovered_text;
    use serde_json::json;

    #[test]
    fn recovered_pairs_shared_numeric_keys() {
        let fitted = json!({"fraction": 0.0886, "sigma_px": 17.6, "offset": [0.0282, 0.03]});
        let truth = json!({"fraction": 0.0998, "sigma_px": 22.93, "offset": [0.02826], "f_number": 16.0});
        // keys in the truth's order (serde_json sorts them); f_number has no fitted value
        assert_eq!(recovered_text(&fitted, &truth), "fraction 0.0886/0.0998, offset 0.0282/0.0283, sigma_px 17.6/22.9");
        assert_eq!(recovered_text(&fitted, &json!({"transfer": "srgb"})), "");
    }
}
