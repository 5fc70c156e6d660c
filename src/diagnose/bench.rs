//! The diagnosis benchmark as library functions: a proof case ([`super::proof`]) rendered,
//! diagnosed and scored against its truth ([`bench_case`]), with the options the proof suite
//! uses ([`proof_options`]). `lensrig diagnose --bench-seeds N` prints these rows as a table;
//! the proof tests assert on them. χ² figures are reduced χ² on the stored axis; the floor
//! ratio is the final residual RMS over the true noise floor.

use super::proof::{floor_ratio, render_case, Case, CaseSpec, UnknownEffect};
use super::{diagnose, DiagnoseError, DiagnoseOptions, Diagnosis};
use crate::estimate::EstimateOptions;

/// Why a benchmark case could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error(transparent)]
    Effect(#[from] UnknownEffect),
    #[error(transparent)]
    Diagnose(#[from] DiagnoseError),
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
    /// Wall-clock seconds of the diagnosis (rendering excluded).
    pub seconds: f64,
    /// Wall-clock seconds of rendering the pair.
    pub render_seconds: f64,
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

/// Three significant digits (one decimal from 10 up).
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

/// Diagnoses one proof case and scores it against the truth. The returned case keeps its
/// captures, truth and true variance; the renderer's noise-free signals and variance maps
/// (`Rendered::clean`, `Rendered::variance`), which only `true_variance` needed, are dropped
/// before the diagnosis, so that the bench's peak memory is the diagnosis' (at 4000×3000 RGB
/// they are 0.9 GB).
///
/// # Errors
/// An unknown effect or a failed diagnosis.
pub fn bench_case(effect: Option<&str>, seed: u64, spec: &CaseSpec, opts: &DiagnoseOptions) -> Result<(BenchRow, Diagnosis, Case), BenchError> {
    let t = std::time::Instant::now();
    let mut case = render_case(effect, seed, spec)?;
    for r in [&mut case.open, &mut case.pinhole] {
        r.clean = Vec::new();
        r.variance = Vec::new();
    }
    let render_seconds = t.elapsed().as_secs_f64();
    let t = std::time::Instant::now();
    let set = effect.map(super::proof::effect_set).transpose()?.unwrap_or_default();
    let mut opts = DiagnoseOptions { pinhole_variance_scale: 1.0 / case.pinhole_frames as f64, ..opts.clone() };
    if let Some(tile) = field_case_tile(&set, spec, &opts) {
        opts.estimate.tile = Some(tile);
    }
    let d = diagnose(&case.open.image, &case.pinhole.image, None, &opts)?;
    let names: Vec<&str> = d.effects.iter().map(|e| e.name.as_str()).collect();
    let (named, correct) = score_names(&set, &names, &d.verdict);
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
        render_seconds,
    };
    Ok((row, d, case))
}

/// The grid the base profile of a case whose effect `set` holds `psf_field_variation` (alone or
/// in a pair) is estimated on ([`FIELD_CASE_GRID`]) where the estimator would choose its own
/// tiling (`opts.estimate.tile` unset, as at every size but the proof suite's). The estimator's
/// grid follows the field it probes (`estimate::lens_tile`: 13 × 9 tiles on the simulator's lens
/// at 1024 × 768 with 45-px kernels), finer than the case's 9 × 7 lens or a real design's 7 × 5
/// grid, so the case would conceal nothing. A profile on a coarser grid than the lens varies on
/// (one estimated at another size, or with `--tile`) is the mismatch the effect names. `None`
/// for every other case, and where the proof suite's tile is given (96 px on 256 × 192: the
/// same 3 × 2 grid).
fn field_case_tile(set: &[&str], spec: &CaseSpec, opts: &DiagnoseOptions) -> Option<usize> {
    if !set.contains(&"psf_field_variation") || opts.estimate.tile.is_some() {
        return None;
    }
    crate::estimate::tile_for_grid(spec.width, spec.height, FIELD_CASE_GRID.0, FIELD_CASE_GRID.1)
}

/// The profile's grid in the `psf_field_variation` case (columns, rows): the proof suite's 3 × 2.
pub const FIELD_CASE_GRID: (usize, usize) = (3, 2);

/// The "named" column and whether it is correct: one concealed effect must be named first; a
/// set of `n` must be the first `n` effects named, in any order (the column shows every name,
/// `+`-joined, so an effect named after them shows); clean data must name none **and** end with
/// the verdict "no mismatch" (an "unexplained" verdict on clean data is a false alarm). Where
/// nothing is named the column shows the verdict's class, "no mismatch" or "unexplained".
fn score_names(set: &[&str], names: &[&str], verdict: &str) -> (String, bool) {
    let class = verdict.split(':').next().unwrap_or(verdict).trim();
    let text = if names.is_empty() { class.to_string() } else { names.join("+") };
    match set.len() {
        0 => (text, names.is_empty() && class == "no mismatch"),
        1 => (names.first().map_or(text, |n| n.to_string()), names.first() == set.first()),
        _ => {
            let (mut a, mut b) = (names[..names.len().min(set.len())].to_vec(), set.to_vec());
            a.sort_unstable();
            b.sort_unstable();
            (text, a == b)
        }
    }
}

/// Options the proof suite uses (small kernels, few iterations).
pub fn proof_options(spec: &CaseSpec) -> DiagnoseOptions {
    DiagnoseOptions { estimate: EstimateOptions { kernel_size: Some(spec.kernel_size), tile: Some(96), max_iterations: 150, joint_iterations: 0, ..Default::default() }, ..Default::default() }
}

#[cfg(test)]
mod tests {
    use super::{field_case_tile, proof_options, recovered_text, score_names, CaseSpec, DiagnoseOptions, FIELD_CASE_GRID};
    use serde_json::json;

    /// The "named" column ([`score_names`]): where nothing is named it shows the verdict's
    /// class, and clean data passes only with the verdict "no mismatch" (an "unexplained" false
    /// alarm named nothing but is not a pass).
    #[test]
    fn unnamed_cases_show_the_verdict_and_clean_needs_no_mismatch() {
        let unexplained = "unexplained: reduced χ² 1.543 remains; residual depends on radius";
        assert_eq!(score_names(&[], &[], "no mismatch: the base model fits to the noise floor"), ("no mismatch".to_string(), true));
        // a false alarm on clean data is not a pass
        assert_eq!(score_names(&[], &[], unexplained), ("unexplained".to_string(), false));
        assert_eq!(score_names(&["misregistration"], &[], unexplained), ("unexplained".to_string(), false));
        assert_eq!(score_names(&["vignetting"], &["vignetting", "black_level"], "explained: …"), ("vignetting".to_string(), true));
        assert_eq!(score_names(&["vignetting", "black_level"], &["black_level", "vignetting"], "explained: …"), ("black_level+vignetting".to_string(), true));
        assert_eq!(score_names(&["vignetting", "black_level"], &[], unexplained), ("unexplained".to_string(), false));
    }

    /// The field case's base profile is on a 3 × 2 grid wherever the estimator would tile by
    /// itself; the proof suite's given tile and every other effect are left alone.
    #[test]
    fn the_field_case_estimates_its_profile_on_a_coarse_grid() {
        let spec = CaseSpec { width: 1024, height: 768, ..CaseSpec::default() };
        let mut opts = DiagnoseOptions::default();
        opts.estimate.tile = None;
        let tile = field_case_tile(&["psf_field_variation"], &spec, &opts).expect("a tile");
        assert_eq!(crate::estimate::tile_grid(1024, 768, tile), FIELD_CASE_GRID);
        assert_eq!(field_case_tile(&["vignetting"], &spec, &opts), None);
        assert_eq!(field_case_tile(&[], &spec, &opts), None);
        assert_eq!(field_case_tile(&["vignetting", "psf_field_variation"], &spec, &opts), Some(tile));
        let proof = proof_options(&CaseSpec::default());
        assert_eq!(field_case_tile(&["psf_field_variation"], &CaseSpec::default(), &proof), None);
        assert_eq!(crate::estimate::tile_grid(256, 192, proof.estimate.tile.expect("the proof tile")), FIELD_CASE_GRID);
    }

    #[test]
    fn recovered_pairs_shared_numeric_keys() {
        let fitted = json!({"fraction": 0.0886, "sigma_px": 17.6, "offset": [0.0282, 0.03]});
        let truth = json!({"fraction": 0.0998, "sigma_px": 22.93, "offset": [0.02826], "f_number": 16.0});
        // keys in the truth's order (serde_json sorts them); f_number has no fitted value
        assert_eq!(recovered_text(&fitted, &truth), "fraction 0.0886/0.0998, offset 0.0282/0.0283, sigma_px 17.6/22.9");
        assert_eq!(recovered_text(&fitted, &json!({"transfer": "srgb"})), "");
    }
}
