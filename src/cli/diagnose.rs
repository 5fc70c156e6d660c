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
use lensrig::diagnose::report::{check_report_dir, write_report, Sources};
use lensrig::diagnose::session::pair_inputs;
use lensrig::diagnose::{diagnose, DiagnoseOptions, Diagnosis};
use lensrig::estimate::session::load_finished;
use lensrig::image::io::{depth_note, read_pair};
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
    /// Report directory: created, or a previous diagnosis's (its files are replaced). A
    /// directory holding anything else (a calibration run, captures) is refused.
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
    /// Catalogue effects never proposed, comma-separated (e.g. `target_tilt`: the verdict on
    /// such a pair as if the catalogue did not model it).
    #[arg(long, value_delimiter = ',')]
    pub exclude_effect: Vec<String>,
    /// Benchmark: run the proof suite over this many seeds and print the table.
    #[arg(long, hide = true)]
    pub bench_seeds: Option<u64>,
    /// Benchmark: first seed.
    #[arg(long, hide = true, default_value_t = 1)]
    pub bench_first_seed: u64,
    /// Benchmark: only this effect (or "clean"); comma-separated for several.
    #[arg(long, hide = true, value_delimiter = ',')]
    pub bench_effect: Option<Vec<String>>,
    /// Benchmark: image size `WIDTHxHEIGHT` (default 256x192, the proof suite's).
    #[arg(long, hide = true)]
    pub bench_size: Option<String>,
    /// Benchmark: RGB pairs through the simulator's chromatic singlet (default monochrome).
    #[arg(long, hide = true)]
    pub bench_rgb: bool,
    /// Benchmark: kernel size of the simulator's lens (default 15; at least 45 at 1024x768).
    #[arg(long, hide = true)]
    pub bench_kernel: Option<usize>,
    /// Benchmark: a truth profile (e.g. from the lens test bed) whose PSFs render the wide-open
    /// capture instead of the simulator's lens; its size, channels and kernel size set the case.
    #[arg(long, hide = true)]
    pub bench_lens: Option<PathBuf>,
    /// Benchmark: the search's progress on stderr at the proof suite's size too (each
    /// proposal's path, gate and comparison; on by default at other sizes).
    #[arg(long, hide = true)]
    pub bench_progress: bool,
    /// No progress output.
    #[arg(long)]
    pub quiet: bool,
}

impl DiagnoseArgs {
    /// The diagnosis options these arguments select.
    pub fn options(&self) -> DiagnoseOptions {
        DiagnoseOptions { estimate: self.estimation.options(), max_effects: self.max_effects, progress: !self.quiet, excluded: self.exclude_effect.clone(), ..Default::default() }
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
    check_report_dir(out)?;
    let (mut o, mut p) = read_pair(open, pinhole)?;
    if let Some(note) = depth_note(open, &o, pinhole, &p) {
        eprintln!("lensrig: note: {note}");
    }
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
        check_report_dir(&out.join(&pair.key)).with_context(|| format!("pair {}", pair.key))?;
    }
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
    eprintln!("verdict: {}", d.verdict);
    for e in &d.effects {
        eprintln!("found {}: {} (evidence: {})", e.name, e.parameters, e.evidence);
    }
    eprintln!("final corrections: {}", serde_json::to_string(&d.final_fit.model.corrections).unwrap_or_default());
    for (name, f) in [("base", &d.base), ("final", &d.final_fit)] {
        eprintln!("{name}: {} pixels, {} parameters, {:.0} effective; χ²/N {:.3}, χ²/(N − p) {:.3}, χ²/(N − p_eff) {:.3}", f.n(), f.params, f.effective_params(), f.chi2() / f.n().max(1) as f64, f.chi2() / (f.n() as f64 - f.params as f64).max(1.0), f.reduced_chi2());
    }
    for n in &d.noise {
        eprintln!("noise {}: a {:.3e} b {:.3e} misfit {:.3}{} | linear law misfit {:.3}; lost detail {:.3}; bins {:?}", n.channel, n.a, n.b, n.misfit, if n.law_tested { "" } else { " (not tested)" }, n.misfit_linear, n.lost_detail, n.curve.bins);
    }
    let sp = |a: &Analysis| a.spectrum.iter().map(|(f, p)| format!("{f:.2}:{p:.2}")).collect::<Vec<_>>().join(" ");
    eprintln!("residual spectrum, base:  {}", sp(&d.base_analysis));
    eprintln!("residual spectrum, final: {}", sp(&d.final_analysis));
    for r in &d.rounds {
        for c in r {
            let [chi2, dbic] = c.figures();
            eprintln!("  {} {chi2} {dbic} {} {}", c.name, c.note, c.parameters);
        }
    }
}

fn print_row(r: &BenchRow) {
    println!("{:<22} {:>4} {:<22} {:>3} {:>10.3} {:>10.3} {:>8.3} {:>6.1}  {}", r.effect, r.seed, r.named, if r.correct { "yes" } else { "NO" }, r.base_chi2, r.final_chi2, r.floor_ratio, r.seconds, r.recovered);
}

fn bench(a: &DiagnoseArgs, seeds: u64) -> Result<()> {
    let spec = bench_spec(a)?;
    let mut opts = proof_options(&spec);
    opts.excluded = a.exclude_effect.clone();
    if spec.width != CaseSpec::default().width || spec.height != CaseSpec::default().height {
        // the estimator's own tiling at other sizes; progress on stderr
        opts.estimate.tile = None;
        opts.progress = !a.quiet;
    }
    opts.progress |= a.bench_progress && !a.quiet;
    let effects: Vec<Option<&str>> = match &a.bench_effect {
        Some(list) => list.iter().map(|e| (e != "clean").then_some(e.as_str())).collect(),
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
            eprintln!("{} seed {seed}: rendering {:.1} s; {}", r.effect, r.render_seconds, d.stage_seconds.iter().map(|t| format!("{} {:.1} s", t.stage, t.wall)).collect::<Vec<_>>().join(", "));
            total += 1;
            ok += r.correct as usize;
            print_row(&r);
        }
    }
    println!("{ok} of {total} cases named correctly");
    if let Some(kb) = peak_memory_kb() {
        println!("peak memory {:.0} MB", kb as f64 / 1024.0);
    }
    Ok(())
}

/// The process's peak resident memory (Linux `VmHWM`), kB.
fn peak_memory_kb() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    s.lines().find_map(|l| l.strip_prefix("VmHWM:")).and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
}

/// The benchmark case's size and optics from the `--bench-*` flags: the proof suite's by
/// default; `--bench-lens` takes size, channels and kernel size from the truth profile.
fn bench_spec(a: &DiagnoseArgs) -> Result<CaseSpec> {
    let mut spec = CaseSpec::default();
    if let Some(s) = &a.bench_size {
        let (w, h) = s.split_once('x').with_context(|| format!("--bench-size {s}: expected WIDTHxHEIGHT"))?;
        spec.width = w.parse().with_context(|| format!("--bench-size {s}: width"))?;
        spec.height = h.parse().with_context(|| format!("--bench-size {s}: height"))?;
        spec.grid = (7, 5);
    }
    if a.bench_rgb {
        spec.channels = 3;
    }
    if let Some(k) = a.bench_kernel {
        check_kernel(Some(k), 3)?;
        spec.kernel_size = k;
    }
    if let Some(dir) = &a.bench_lens {
        let p = Profile::load(dir).with_context(|| format!("reading the truth profile {}", dir.display()))?;
        spec = match spec.through_truth(&p) {
            Ok(s) => s,
            Err(n) => bail!("{}: the truth profile has {n} channel(s); the benchmark renders RGB", dir.display()),
        };
    }
    if spec.width < 4 * spec.kernel_size || spec.height < 4 * spec.kernel_size {
        bail!("the benchmark image {}x{} is too small for {}-px kernels", spec.width, spec.height, spec.kernel_size);
    }
    Ok(spec)
}
