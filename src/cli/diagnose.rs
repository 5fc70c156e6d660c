//! `lensrig diagnose`: arguments and the command. Also a hidden benchmark mode
//! (`--bench-seeds N`) that renders the proof suite ([`lensrig::diagnose::bench`]) and prints
//! the table (effect, named, base χ², final χ², floor ratio) instead of reading files.

use super::args::EstimateArgs;
use super::check_kernel;
use anyhow::{bail, Context, Result};
use clap::Args;
use lensrig::diagnose::analysis::Analysis;
use lensrig::diagnose::bench::{bench_case, proof_options, BenchRow};
use lensrig::diagnose::proof::{CaseSpec, CONCEALED};
use lensrig::diagnose::report::{write_report, Sources};
use lensrig::diagnose::session::pair_inputs;
use lensrig::diagnose::{diagnose, DiagnoseOptions, Diagnosis};
use lensrig::estimate::session::load_finished;
use lensrig::image::io::read_pair;
use lensrig::image::{Image, Transfer};
use lensrig::profile::Profile;
use std::path::{Path, PathBuf};

#[derive(Args, Debug, Clone)]
#[command(mut_arg("joint_iterations", |a| a.default_value("0")))]
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
    /// The base estimate's flags (used when no --profile is given).
    #[command(flatten)]
    pub estimation: EstimateArgs,
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

impl DiagnoseArgs {
    /// The diagnosis options these arguments select.
    pub fn options(&self) -> DiagnoseOptions {
        DiagnoseOptions { estimate: self.estimation.options(), max_effects: self.max_effects, progress: !self.quiet, ..Default::default() }
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
    check_kernel(a.estimation.kernel, 3)?;
    let (mut o, mut p) = read_pair(open, pinhole)?;
    o.transfer = a.transfer;
    p.transfer = a.transfer;
    let profile = match &a.profile {
        Some(dir) => Some(Profile::load(dir)?),
        None => None,
    };
    let mut opts = a.options();
    if let Some(f) = &a.frames {
        if f.len() != 2 || f.contains(&0) {
            bail!("--frames takes two positive counts, wide-open then pinhole, e.g. --frames 1,16");
        }
        opts.pinhole_variance_scale = f[0] as f64 / f[1] as f64;
    }
    let files = Files { open, pinhole, profile: a.profile.as_deref(), out };
    diagnose_files(&o, &p, profile.as_ref(), &opts, &files)
}

/// Where a diagnosis reads from and writes to (for the report and the messages).
struct Files<'a> {
    open: &'a Path,
    pinhole: &'a Path,
    profile: Option<&'a Path>,
    out: &'a Path,
}

fn diagnose_files(o: &Image, p: &Image, profile: Option<&Profile>, opts: &DiagnoseOptions, f: &Files) -> Result<()> {
    let d = diagnose(o, p, profile, opts).with_context(|| format!("diagnosing {} against {}", f.open.display(), f.pinhole.display()))?;
    let src = Sources { open: f.open.display().to_string(), pinhole: f.pinhole.display().to_string(), profile: f.profile.map(|p| p.display().to_string()) };
    write_report(&d, f.out, &src)?;
    let names: Vec<&str> = d.effects.iter().map(|e| e.name.as_str()).collect();
    println!(
        "{}; reduced χ² {:.3} → {:.3}; effects: {}; report: {}",
        d.verdict,
        d.base.reduced_chi2(),
        d.final_fit.reduced_chi2(),
        if names.is_empty() { "none".to_string() } else { names.join(", ") },
        f.out.join("index.html").display()
    );
    Ok(())
}

/// `--session`: every finished pair of a capture session, each into `out/<pair key>/`
/// ([`lensrig::diagnose::session`]: transfer curve, dark level and frame counts from the
/// frames' sidecars).
fn run_session(a: &DiagnoseArgs, session: &Path, out: &Path) -> Result<()> {
    let rec = load_finished(session)?;
    for pair in &rec.pairs {
        let (sp, opts) = pair_inputs(session, pair, &a.options())?;
        if !a.quiet {
            eprintln!(
                "diagnosing pair {} (stage {} mm; {} / {} frames averaged; noise model from {})",
                pair.key,
                pair.stage_mm,
                sp.open_record.frames_averaged,
                sp.pinhole_record.frames_averaged,
                if opts.repeat_noise.is_some() { "the repeated frames" } else { "the residual" }
            );
        }
        let files = Files { open: &sp.open_path, pinhole: &sp.pinhole_path, profile: None, out: &out.join(&pair.key) };
        diagnose_files(&sp.open, &sp.pinhole, None, &opts, &files).with_context(|| format!("pair {}", pair.key))?;
    }
    Ok(())
}

/// `--bench-effect`'s details on stderr: the truth, the noise fits, the residual spectra and
/// every candidate of every round.
fn print_details(truth: &serde_json::Value, d: &Diagnosis) {
    eprintln!("truth {truth}");
    for n in &d.noise {
        eprintln!("noise {}: a {:.3e} b {:.3e} misfit {:.3} | linear law misfit {:.3}; bins {:?}", n.channel, n.a, n.b, n.misfit, n.misfit_linear, n.curve.bins);
    }
    let sp = |a: &Analysis| a.spectrum.iter().map(|(f, p)| format!("{f:.2}:{p:.2}")).collect::<Vec<_>>().join(" ");
    eprintln!("residual spectrum, base:  {}", sp(&d.base_analysis));
    eprintln!("residual spectrum, final: {}", sp(&d.final_analysis));
    for r in &d.rounds {
        for c in r {
            eprintln!("  {} {:.4} {:.1} {} {}", c.name, c.reduced_chi2, c.delta_bic, c.note, c.parameters);
        }
    }
}

fn print_row(r: &BenchRow) {
    println!("{:<22} {:>4} {:<22} {:>3} {:>10.3} {:>10.3} {:>8.3} {:>6.1}  {}", r.effect, r.seed, r.named, if r.correct { "yes" } else { "NO" }, r.base_chi2, r.final_chi2, r.floor_ratio, r.seconds, r.recovered);
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
            let (r, d, c) = bench_case(e, seed, &spec, &opts)?;
            if a.bench_effect.is_some() {
                print_details(&c.truth, &d);
            }
            total += 1;
            ok += r.correct as usize;
            print_row(&r);
        }
    }
    println!("{ok} of {total} cases named correctly");
    Ok(())
}
