//! The diagnosis proof suite: for each catalogue effect, a pair rendered by the simulator with
//! that effect concealed at a randomised magnitude; the report must name it first, end within
//! 1.10× of the true noise floor, and recover its parameters; clean data must give "no
//! mismatch". Pairs of effects concealed together must both be named; a target tilt with its
//! model left out of the catalogue must be reported "unexplained", and named once it is in. Plus the report files, the corrected profile, the CLI entry point and the HTML
//! in a headless browser.

mod common;

use lensrig::diagnose::bench::{bench_case, proof_options, BenchRow};
use lensrig::diagnose::model::apply_corrections;
use lensrig::diagnose::proof::CaseSpec;
use lensrig::diagnose::Diagnosis;
use lensrig::fsutil::Overwrite;
use lensrig::image::io::{read_image, write_png16};
use lensrig::optics::capture::Sensor;
use lensrig::profile::Profile;
use std::path::Path;

const FLOOR: f64 = 1.10;

fn case(effect: Option<&str>, seed: u64) -> (BenchRow, Diagnosis, lensrig::diagnose::proof::Case) {
    let spec = CaseSpec::default();
    bench_case(effect, seed, &spec, &proof_options(&spec)).expect("diagnosis runs")
}

fn check_named(effect: &str, seed: u64) -> (Diagnosis, lensrig::diagnose::proof::Case) {
    check_named_floor(effect, seed, FLOOR)
}

fn check_named_floor(effect: &str, seed: u64, floor: f64) -> (Diagnosis, lensrig::diagnose::proof::Case) {
    let (row, d, c) = case(Some(effect), seed);
    let names: Vec<&str> = d.effects.iter().map(|e| e.name.as_str()).collect();
    assert_eq!(names.first().copied(), Some(effect), "{effect} (seed {seed}, truth {}): named {names:?}; rounds {:?}", c.truth, d.rounds);
    assert!(row.floor_ratio <= floor, "{effect}: final residual {:.3}× the true noise floor", row.floor_ratio);
    let e = &d.effects[0];
    assert!(!e.evidence.is_empty() && !e.location.is_empty() && e.after.reduced_chi2 < e.before.reduced_chi2);
    (d, c)
}

#[test]
fn clean_data_is_no_mismatch_and_the_noise_model_matches_the_sensor() {
    let (row, d, c) = case(None, 1);
    assert!(d.effects.is_empty(), "false alarm: {:?}", d.effects.iter().map(|e| &e.name).collect::<Vec<_>>());
    assert!(d.verdict.starts_with("no mismatch"), "{}", d.verdict);
    assert!(row.floor_ratio <= FLOOR, "base residual {:.3}× the floor", row.floor_ratio);
    // the noise law against the simulator's sensor at mid level
    let sensor = Sensor::default();
    for l in [0.15f32, 0.35] {
        let want = sensor.variance(l) as f64;
        let got = d.noise[0].a * l as f64 + d.noise[0].b;
        assert!((got / want - 1.0).abs() < 0.20, "variance at {l}: {got:.3e} vs true {want:.3e}");
    }
    // the predicted floor against the true one (propagated pinhole noise included)
    let true_floor: f64 = {
        let (mut s, mut n) = (0.0, 0);
        for (i, &m) in d.final_fit.eval[0].iter().enumerate() {
            if m {
                s += c.true_variance[0].data[i] as f64;
                n += 1;
            }
        }
        (s / n as f64).sqrt()
    };
    let rendered = true_noise_reduced_chi2(&d.final_fit, &c);
    // the statistic the tilt test bounds from below (measured 0.972 here)
    let bound = lensrig::diagnose::DiagnoseOptions::default().consistent;
    assert!(rendered <= bound, "reduced χ² on the rendered noise {rendered:.4} above {bound}");
    let floor = d.final_fit.noise_rms();
    assert!((floor / true_floor - 1.0).abs() < 0.10, "noise floor {floor:.3e} vs true {true_floor:.3e}");
}

/// A kernel window large against the image (31-px kernels on 256×192: the nominal kernel count
/// is 16% of the evaluated pixels). Clean data must be consistent with noise once the reduced
/// χ² subtracts the effective degrees of freedom, where the nominal count would call it a
/// mismatch; a concealed vignetting must still leave the base model inconsistent and be named.
/// The kernel budget is raised to 400 iterations: with 80, 31-px kernels are not converged on
/// this pair (χ²/N 1.6, a real misfit, not a count).
fn big_kernel_case(effect: Option<&str>) -> (BenchRow, Diagnosis, lensrig::diagnose::proof::Case) {
    let spec = CaseSpec { kernel_size: 31, ..CaseSpec::default() };
    let mut opts = proof_options(&spec);
    opts.base_fit.kernel_iterations = 400;
    bench_case(effect, 31, &spec, &opts).expect("diagnosis runs")
}

#[test]
fn big_kernels_on_clean_data_are_consistent_with_effective_dof() {
    let (row, d, _) = big_kernel_case(None);
    let b = &d.base;
    let nominal = b.chi2() / (b.n() as f64 - b.params as f64);
    assert!(b.params as f64 > 0.15 * b.n() as f64, "nominal {} of {} pixels", b.params, b.n());
    assert!(nominal > 1.10, "the nominal count would not inflate χ²/dof here: {nominal:.3}");
    eprintln!("big kernels, clean: {} pixels, {} nominal, {:.0} effective; χ²/(N − p) {nominal:.3}, χ²/(N − p_eff) {:.3}", b.n(), b.params, b.effective_params(), b.reduced_chi2());
    assert!(b.effective_params() < 0.5 * b.params as f64, "effective {:.0} of {} nominal", b.effective_params(), b.params);
    assert!(d.verdict.starts_with("no mismatch"), "{} (nominal χ²/dof {nominal:.3}, effective {:.3})", d.verdict, b.reduced_chi2());
    assert!(row.floor_ratio <= FLOOR, "base residual {:.3}× the floor", row.floor_ratio);
}

#[test]
fn big_kernels_with_vignetting_are_inconsistent_with_effective_dof() {
    let (_, d, c) = big_kernel_case(Some("vignetting"));
    assert!(d.base.reduced_chi2() > 1.10, "base χ²/dof {:.3} (truth {})", d.base.reduced_chi2(), c.truth);
    assert_eq!(d.effects.first().map(|e| e.name.as_str()), Some("vignetting"), "rounds {:?}", d.rounds);
}

#[test]
fn vignetting_is_named_and_its_gain_recovered() {
    let (d, c) = check_named("vignetting", 2);
    let p = &d.effects[0].parameters;
    let g = |v: &serde_json::Value, r2: f64| 1.0 + v["k1"].as_f64().unwrap() * r2 + v["k2"].as_f64().unwrap() * r2 * r2 + v["k3"].as_f64().unwrap() * r2.powi(3);
    for r2 in [0.25, 0.5, 1.0] {
        assert!((g(p, r2) / g(&c.truth, r2) - 1.0).abs() < 0.02, "gain at r²={r2}: {p} vs {}", c.truth);
    }
    assert!((p["k1"].as_f64().unwrap() / c.truth["k1"].as_f64().unwrap() - 1.0).abs() < 0.25, "k1 {p} vs {}", c.truth);
}

#[test]
fn illumination_gradient_is_named_and_recovered() {
    let (d, c) = check_named("illumination_gradient", 3);
    let p = &d.effects[0].parameters;
    for k in ["gx", "gy"] {
        assert!((p[k].as_f64().unwrap() - c.truth[k].as_f64().unwrap()).abs() < 0.01, "{k}: {p} vs {}", c.truth);
    }
}

#[test]
fn black_level_is_named_and_recovered() {
    let (d, c) = check_named("black_level", 4);
    let got = d.effects[0].parameters["offset"][0].as_f64().unwrap();
    let want = c.truth["offset"][0].as_f64().unwrap();
    assert!((got - want).abs() < 0.003, "offset {got} vs {want}");
}

#[test]
fn tone_curve_is_named() {
    let (d, _) = check_named("tone_curve", 5);
    assert_eq!(d.effects[0].parameters["transfer"], "srgb");
}

/// The glare fraction and width against the rendered ones. Both `veiling_glare` and
/// `black_level` take the kernels' common flat floor (`fit::remove_common_floor`), so the halo
/// is no longer split between the kernels and the glare term (the fraction came out at half
/// the truth before). Measured (seed 6, and seeds 21/22 of the bench): fraction −11%, +15%,
/// +19%; width −23%, −22%, −28% (a narrower halo with a little more light fits the same).
#[test]
fn veiling_glare_is_named_and_its_fraction_recovered() {
    let (d, c) = check_named("veiling_glare", 6);
    let p = &d.effects[0].parameters;
    let (got, want) = (p["fraction"].as_f64().unwrap(), c.truth["fraction"].as_f64().unwrap());
    assert!((got / want - 1.0).abs() < 0.25, "glare fraction {got} vs {want}");
    let (got, want) = (p["sigma_px"].as_f64().unwrap(), c.truth["sigma_px"].as_f64().unwrap());
    assert!((got / want - 1.0).abs() < 0.35, "glare width {got} vs {want} px");
}

/// Named, the rotation within 10% (the kernels' centroid fixed point; seed 7 measured +1.4%,
/// bench seed 21 −4.6%), and the final residual at the floor. The scale is not checked: the
/// lens's coma moves kernel centroids in proportion to the radius, like a magnification
/// change, so one pair gives the scale only relative to the lens's own.
#[test]
fn misregistration_is_named_and_its_rotation_recovered() {
    let (row, d, c) = case(Some("misregistration"), 7);
    assert_eq!(d.effects.first().map(|e| e.name.as_str()), Some("misregistration"), "rounds {:?}", d.rounds);
    let got = d.effects[0].parameters["rotation_deg"].as_f64().unwrap();
    let want = c.truth["rotation_deg"].as_f64().unwrap();
    assert!((got / want - 1.0).abs() < 0.10, "rotation {got} vs {want}");
    assert!(row.floor_ratio <= FLOOR, "final residual {:.3}× the floor", row.floor_ratio);
}

/// A misregistration the kernels almost absorb: seed 21 rotates the 256×192 frame by 0.32°, the
/// corners by under a pixel, and the current kernels moved by the centroids' similarity do not
/// pass the start gate. The start re-estimated under the map must still find it: the kernels'
/// rotation is significant (t ≈ −24), so the registered path's bound is a quarter pixel
/// (`candidates::registered_bound`); at 1 px, before session 46, this case ended "unexplained"
/// at 1.088× the floor. The start's scale is refined by χ² (`registered::refine`):
/// the centroids' scale (+0.00137, the lens's coma included, against −0.00282 rendered) left the
/// fit at χ²/dof 1.106, above the consistency bound, and the verdict "unexplained after
/// misregistration" (session 46).
#[test]
fn a_sub_pixel_misregistration_is_named_and_its_rotation_recovered() {
    let (row, d, c) = case(Some("misregistration"), 21);
    let want = c.truth["rotation_deg"].as_f64().unwrap();
    let corner = 0.5 * (256f64.hypot(192.0)) * want.to_radians().abs();
    assert!(corner < 1.0, "the rendered rotation moves the corners by {corner:.2} px: not a sub-pixel case");
    assert_eq!(d.effects.first().map(|e| e.name.as_str()), Some("misregistration"), "verdict {}; rounds {:?}", d.verdict, d.rounds);
    let got = d.effects[0].parameters["rotation_deg"].as_f64().unwrap();
    assert!((got / want - 1.0).abs() < 0.10, "rotation {got} vs {want}");
    assert!(row.floor_ratio <= FLOOR, "final residual {:.3}× the floor", row.floor_ratio);
    assert!(row.final_chi2 <= 1.10 && !d.verdict.contains("unexplained"), "χ²/dof {:.3}: {}", row.final_chi2, d.verdict);
    let (scale, want) = (d.effects[0].parameters["scale"].as_f64().unwrap(), c.truth["scale"].as_f64().unwrap());
    assert!((scale - want).abs() < 0.0008, "scale {scale:+.5} vs {want:+.5} rendered");
}

#[test]
fn saturation_is_named() {
    check_named("saturation", 8);
}

#[test]
fn psf_field_variation_is_named() {
    check_named("psf_field_variation", 9);
}

/// Named first and at the floor: the reference's blur is modelled as the band-averaged Airy
/// pattern times a Gaussian of the lens's residual aberrations at the stop
/// (`aberration_sigma_px`). What the data determine is the transfer from the reference to the
/// wide-open capture, `K̂/D̂` (the fitted kernels over the fitted reference PSF): any `D`
/// predicts alike once the kernels absorb the difference, as long as they stay non-negative.
/// With converged kernels (the tangent step) the fit at f/11 (this seed) puts more of the blur
/// in both: kernels and reference 26 % lower at 0.30 cycles/px than rendered, their ratio
/// within 0.6 % (reference MTF50 0.230 against 0.262 rendered, Airy radius 0.71 against
/// 1.49 px). So the figure checked is `K̂/D̂`, mean over tiles along a pixel row, against the
/// rendered `K̂/D̂` on 0.05–0.40 cycles/px (where the rendered reference passes ≥ 34 %):
/// within [`TRANSFER_TOLERANCE`] (measured 0.85 %; the base model, `D = δ`, misses by 5.9 %
/// at 0.40 cycles/px, where the reference's blur shows).
#[test]
fn pinhole_diffraction_is_named_and_its_transfer_recovered() {
    use lensrig::diagnose::proof::kernel_modulation;
    let (row, d, c) = case(Some("pinhole_diffraction"), 1);
    assert_eq!(d.effects.first().map(|e| e.name.as_str()), Some("pinhole_diffraction"), "rounds {:?}", d.rounds);
    let e = &d.effects[0];
    assert!(e.after.reduced_chi2 < 0.85 * e.before.reduced_chi2, "{:?} → {:?}", e.before.reduced_chi2, e.after.reduced_chi2);
    assert!(e.evidence.contains("non-negative kernel"), "{}", e.evidence);
    let psf = d.final_fit.model.corrections.pinhole_diffraction.as_ref().expect("the correction is in the final model").channel(0).0;
    let fitted = &d.final_fit.model.grid.kernels[0];
    let (open, pin) = (c.open.psfs.as_ref().expect("rendered PSFs"), c.pinhole.psfs.as_ref().expect("rendered PSFs"));
    let base = &d.base.model.grid.kernels[0];
    let mut worst = (0.0f64, 0.0f64, 0.0f64);
    for i in 1..=8 {
        let f = 0.05 * i as f64;
        let want = kernel_modulation(&open.kernels[0], f) / kernel_modulation(&pin.kernels[0], f);
        let got = kernel_modulation(fitted, f) / psf.transfer(f, 0.0);
        let err = (got / want - 1.0).abs();
        eprintln!("K̂/D̂ at {f:.2} cycles/px: fitted {got:.4}, rendered {want:.4} (base model {:.4})", kernel_modulation(base, f));
        if err > worst.0 {
            worst = (err, f, got / want);
        }
    }
    assert!(worst.0 < TRANSFER_TOLERANCE, "transfer from the reference to the wide-open capture off by {:.1}% at {:.2} cycles/px; parameters {}, truth {}", 100.0 * worst.0, worst.1, e.parameters, c.truth);
    let r = e.parameters["airy_radius_px"][0].as_f64().unwrap();
    assert!(r > 0.0 && r < 2.0 * c.truth["airy_radius_px"].as_f64().unwrap(), "Airy radius {r}");
    assert!(e.parameters["aberration_sigma_px"].as_f64().is_some_and(|v| (0.0..=1.5).contains(&v)), "{}", e.parameters);
    assert!(row.floor_ratio <= FLOOR, "final residual {:.3}× the floor", row.floor_ratio);
}

/// Relative error allowed on the fitted `K̂/D̂` of `pinhole_diffraction`: between the fit's
/// measured error (0.85 %, seed 1) and the base model's (5.9 %).
const TRANSFER_TOLERANCE: f64 = 0.025;

/// Two effects concealed together (issue 17): both named first, in either order, and the fit
/// at the floor (the verdict is not checked: on vignetting + black level, seed 12, it reads
/// "unexplained" at reduced χ² 0.994 because the noise curve misfits its Poisson–Gaussian law
/// by 18 %, above `consistent_noise`). `extra`: whether another effect may follow them (see
/// `misregistration_and_pinhole_diffraction_are_both_named`).
fn check_pair(pair: &str, seed: u64, extra: bool) -> (Diagnosis, lensrig::diagnose::proof::Case) {
    let (row, d, c) = case(Some(pair), seed);
    let all: Vec<&str> = d.effects.iter().map(|e| e.name.as_str()).collect();
    assert!(extra || all.len() == 2, "{pair} (seed {seed}): named {all:?}; rounds {:?}", d.rounds);
    let mut named: Vec<&str> = all[..all.len().min(2)].to_vec();
    named.sort_unstable();
    let mut want: Vec<&str> = pair.split('+').collect();
    want.sort_unstable();
    assert_eq!(named, want, "{pair} (seed {seed}, truth {}): rounds {:?}", c.truth, d.rounds);
    assert!(row.correct, "{pair}: bench row {row:?}");
    assert!(row.floor_ratio <= FLOOR, "{pair}: final residual {:.3}× the true noise floor", row.floor_ratio);
    (d, c)
}

/// Both named and at the floor. The offset itself is not checked: with a radial gain in the
/// model it trades off against the gain's higher terms on this field (seed 12: offset 0.029
/// against 0.038 rendered, `k2` 0.3 against 0.01; docs/diagnosis.md).
#[test]
fn vignetting_and_black_level_are_both_named() {
    check_pair("vignetting+black_level", 12, false);
}

#[test]
fn veiling_glare_and_tone_curve_are_both_named() {
    check_pair("veiling_glare+tone_curve", 12, false);
}

/// Both named first. A third, small additive term may follow: on bench seeds 21–23 an offset
/// of 0.0008–0.0018 of full scale (`black_level`, or `veiling_glare` at the widest halo
/// searched, which over this field is the same) was accepted after them (cause not found;
/// docs/diagnosis.md); it is bounded here.
#[test]
fn misregistration_and_pinhole_diffraction_are_both_named() {
    let (d, _) = check_pair("misregistration+pinhole_diffraction", 12, true);
    for e in &d.effects[2..] {
        let small = e.parameters["offset"][0].as_f64().map_or(true, |o| o.abs() < 0.003) && e.parameters["fraction"].as_f64().map_or(true, |f| f < 0.02);
        assert!(["black_level", "veiling_glare"].contains(&e.name.as_str()) && small, "third effect {} {}", e.name, e.parameters);
    }
}

/// A target tilted between the captures (a keystone) with `target_tilt` left out of the
/// catalogue: the verdict is "unexplained" because χ² remains (not for the noise law), says
/// where the residual is and what it depends on, and the fit stays above the floor. "Above the
/// floor" is tested on χ², not on the residual's RMS: the keystone's misfit sits at the corners
/// and on edges, and a finer kernel grid (`psf_field_variation`, the nearest catalogue effect)
/// follows it at its tile centres, so the field-wide RMS is only 1.027× the true floor
/// (clean data: 0.98×) while χ² is well above its sampling spread `√(2/(N − p_eff))` (0.007):
/// reduced χ² 1.189 on the measured noise curve and 1.210 on the rendered noise (clean data:
/// 0.990 and 0.972). Both must exceed the verdict's consistency bound by three sampling
/// standard deviations.
#[test]
fn target_tilt_is_unexplained_without_its_model() {
    let spec = CaseSpec::default();
    let mut opts = proof_options(&spec);
    opts.excluded = vec!["target_tilt".into()];
    let (_, d, c) = bench_case(Some("target_tilt"), 13, &spec, &opts).expect("diagnosis runs");
    assert!(d.verdict.starts_with("unexplained") && d.verdict.contains("remains"), "{} (truth {})", d.verdict, c.truth);
    assert!(d.verdict.contains("worst at tile") && d.verdict.contains("residual depends on"), "{}", d.verdict);
    assert!(d.effects.iter().all(|e| e.name != "target_tilt"));
    let f = &d.final_fit;
    let dof = f.n() as f64 - f.effective_params();
    let bound = opts.consistent + 3.0 * (2.0 / dof).sqrt();
    let rendered = true_noise_reduced_chi2(f, &c);
    eprintln!("tilt without its model: reduced χ² {:.4} (measured curve), {rendered:.4} (rendered noise), bound {bound:.4}", f.reduced_chi2());
    assert!(f.reduced_chi2() > bound, "reduced χ² {:.4} ≤ {bound:.4}: the excluded effect was absorbed", f.reduced_chi2());
    assert!(rendered > bound, "χ² on the rendered noise {rendered:.4} ≤ {bound:.4}: the excluded effect was absorbed");
}

/// `Σ r² / σ²_true / (N − p_eff)` over the fit's evaluated pixels: the reduced χ² against the
/// case's rendered noise variance instead of the measured curve.
fn true_noise_reduced_chi2(f: &lensrig::diagnose::fit::Fit, c: &lensrig::diagnose::proof::Case) -> f64 {
    let mut s = 0.0f64;
    for ch in 0..f.eval.len() {
        for (i, &m) in f.eval[ch].iter().enumerate() {
            if m {
                let r2 = (c.open.image.planes[ch].data[i] as f64 - f.predicted[ch].data[i] as f64).powi(2);
                s += r2 / c.true_variance[ch].data[i] as f64;
            }
        }
    }
    s / (f.n() as f64 - f.effective_params())
}

/// The same pair with `target_tilt` in the catalogue: named first, the perspective row within
/// 10% of the rendered one, and the fit at the floor (≤ 1.10× the true floor). The verdict is
/// not checked: this seed ends at reduced χ² 1.106, just above the consistency bound, so it
/// reads "unexplained … after target_tilt" (docs/diagnosis.md).
#[test]
fn target_tilt_is_named_and_its_keystone_recovered() {
    let (d, c) = check_named("target_tilt", 13);
    let p = &d.effects[0].parameters;
    let (g, h) = (c.truth["g"].as_f64().unwrap(), c.truth["h"].as_f64().unwrap());
    let err = (p["g"].as_f64().unwrap() - g).hypot(p["h"].as_f64().unwrap() - h) / g.hypot(h);
    assert!(err < 0.10, "perspective row {p} vs truth {}", c.truth);
}

/// The report files, the corrected profile through `apply_corrections`, the CLI entry point,
/// and the HTML in headless Chromium when it is installed.
#[test]
fn report_profile_cli_and_browser() {
    let spec = CaseSpec::default();
    let c = lensrig::diagnose::proof::render_case(Some("vignetting"), 11, &spec).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let open = dir.path().join("open.png");
    let pin = dir.path().join("pinhole.png");
    write_png16(&open, &c.open.image, Overwrite::Replace).unwrap();
    write_png16(&pin, &c.pinhole.image, Overwrite::Replace).unwrap();
    let out = dir.path().join("report");
    let kernel = spec.kernel_size.to_string();
    let diagnose = |open: &Path| common::run(&["diagnose", "--open", open.to_str().unwrap(), "--pinhole", pin.to_str().unwrap(), "--out", out.to_str().unwrap(), "--kernel", &kernel, "--tile", "96", "--quiet"]);
    let o = diagnose(&open);
    assert!(o.status.success(), "diagnose: {}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["effects"][0]["name"], "vignetting");
    for key in ["noise", "base", "final", "effects"] {
        assert!(!report[key].is_null(), "report.json lacks {key}");
    }
    assert!(report["final"]["reduced_chi2"].as_f64().unwrap() < report["base"]["reduced_chi2"].as_f64().unwrap());
    let html = std::fs::read_to_string(out.join("index.html")).unwrap();
    assert!(html.contains("residual power spectrum"), "index.html lacks the residual spectrum");
    assert!(html.contains("Low-band test of the final model"), "index.html lacks the low-band test's line");
    let o = read_image(&open).unwrap();
    for f in ["predicted_base.png", "predicted_final.png"] {
        let p = read_image(&out.join(f)).unwrap();
        assert_eq!((p.width(), p.height(), p.channel_count(), p.format), (o.width(), o.height(), o.channel_count(), o.format), "{f}");
    }
    // the corrected profile predicts what the report predicted
    let prof = Profile::load(&out.join("profile")).unwrap();
    assert!(prof.meta.corrections.contains_key("vignetting"));
    let pred = apply_corrections(&prof, &read_image(&pin).unwrap()).unwrap();
    let fin = read_image(&out.join("predicted_final.png")).unwrap();
    let (w, h) = (o.width(), o.height());
    let mut worst = 0.0f32;
    for y in 10..h - 10 {
        for x in 10..w - 10 {
            worst = worst.max((pred.planes[0].get(x, y) - fin.planes[0].get(x, y)).abs());
        }
    }
    assert!(worst < 2e-3, "apply_corrections differs from the report's prediction by {worst}");
    // an unreadable input names the file
    let missing = dir.path().join("missing.png");
    let e = common::fails_one_line(&["diagnose", "--open", missing.to_str().unwrap(), "--pinhole", pin.to_str().unwrap(), "--out", out.to_str().unwrap(), "--kernel", &kernel, "--tile", "96", "--quiet"]);
    assert!(e.contains("missing.png"), "{e}");
    // a directory holding another command's report is refused before any work, and kept
    let foreign = dir.path().join("calibration");
    std::fs::create_dir_all(&foreign).unwrap();
    std::fs::write(foreign.join("index.html"), "calibration report").unwrap();
    let e = common::fails_one_line(&["diagnose", "--open", open.to_str().unwrap(), "--pinhole", pin.to_str().unwrap(), "--out", foreign.to_str().unwrap(), "--kernel", &kernel, "--tile", "96", "--quiet"]);
    assert!(e.contains("index.html") && e.contains("not a diagnosis report"), "{e}");
    assert_eq!(std::fs::read_to_string(foreign.join("index.html")).unwrap(), "calibration report");
    assert_eq!(std::fs::read_dir(&foreign).unwrap().count(), 1, "files were written into the foreign directory");

    // headless browser
    let browser = ["chromium", "chromium-browser", "google-chrome"].iter().find(|b| std::process::Command::new(b).arg("--version").output().is_ok_and(|o| o.status.success()));
    let Some(browser) = browser else {
        eprintln!("SKIPPED browser check: no chromium found (apt-get install -y chromium)");
        return;
    };
    let url = format!("file://{}", out.join("index.html").display());
    let o = std::process::Command::new(browser)
        .args(["--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=5000", "--dump-dom", &url])
        .output()
        .expect("run chromium");
    let dom = String::from_utf8_lossy(&o.stdout);
    assert!(dom.contains("vignetting") && dom.contains("Verdict"), "DOM lacks the effect: {}", &dom[..dom.len().min(500)]);
    assert!(dom.contains("data-images-loaded=\"4/4\""), "not every image loaded: {}", dom.lines().find(|l| l.contains("<body")).unwrap_or(""));
    assert!(dom.matches("<svg").count() >= 5, "plots missing");
}

/// `diagnose --session`: a capture session from the simulated rig (grbl firmware on a pty and
/// the mock camera), every pair diagnosed into OUT/<pair key>/ with its metadata's transfer
/// curve, dark level and frame counts; and `--frames` validated.
#[test]
fn diagnose_reads_a_capture_session() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = common::mock_config(dir.path(), |text| {
        text.replace("width = 384", "width = 160")
            .replace("height = 288", "height = 120")
            .replace("positions = [-20.0, -40.0, -60.0]", "positions = [-20.0]")
            .replace("frames_to_average = 16", "frames_to_average = 4")
    });
    let session = dir.path().join("session");
    let o = common::bin().args(["capture", "--rig", cfg.to_str().unwrap(), "--out", session.to_str().unwrap(), "--quiet"]).output().unwrap();
    assert!(o.status.success(), "capture: {}", String::from_utf8_lossy(&o.stderr));
    let out = dir.path().join("diag");
    let o = common::bin().args(["diagnose", "--session", session.to_str().unwrap(), "--out", out.to_str().unwrap(), "--kernel", "15", "--max-effects", "1"]).output().unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "diagnose --session: {stderr}");
    assert!(stderr.contains("4 / 4 frames averaged"), "frame counts not read from the metadata: {stderr}");
    assert!(stderr.contains("noise model from the repeated frames"), "{stderr}");
    let pairs: Vec<_> = std::fs::read_dir(&out).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(pairs.len(), 1, "{pairs:?}");
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(pairs[0].join("report.json")).unwrap()).unwrap();
    assert!(report["effects"].is_array());
    // the noise model is the mock sensor's temporal noise over the 4 averaged frames: the
    // variance of the average against the law of `rig-configs/mock.toml`'s sensor (gain 0 dB,
    // full well and read noise from the mock optics), divided by the frame count
    let noise = &report["noise"][0];
    assert_eq!(noise["source"], "repeated frames", "{noise}");
    let rig = lensrig::rig::config::load(&cfg).unwrap();
    let sensor = &lensrig::rig::camera::mock::MockOptics::from_config(&rig).unwrap().sensor;
    let g = 10f64.powf(rig.camera.gain / 20.0);
    let mut checked = 0;
    for bin in noise["curve"]["bins"].as_array().unwrap() {
        let (level, var) = (bin[0].as_f64().unwrap(), bin[1].as_f64().unwrap());
        if level > 0.05 {
            checked += 1;
            let want = (g * level / sensor.full_well_e + (sensor.read_noise_e * g / sensor.full_well_e).powi(2)) / 4.0;
            assert!((var / want - 1.0).abs() < 0.10, "level {level:.3}: {var:.3e} vs {want:.3e}");
        }
    }
    assert!(checked >= 4, "only {checked} noise bins above 5% of full scale");
    assert!(report["final"]["reduced_chi2"].as_f64().unwrap() <= report["base"]["reduced_chi2"].as_f64().unwrap() + 1e-9);
    let pair_dirs: Vec<_> = std::fs::read_dir(session.join("pairs")).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(pair_dirs.len(), 1, "{pair_dirs:?}");
    let open = read_image(&pair_dirs[0].join("open.png")).unwrap();
    let pred = read_image(&pairs[0].join("predicted_final.png")).unwrap();
    assert_eq!((pred.width(), pred.height(), pred.channel_count()), (open.width(), open.height(), open.channel_count()));
    // a bad --frames is refused with a one-line cause
    let o = common::run(&["diagnose", "--open", "a.png", "--pinhole", "b.png", "--out", "x", "--frames", "0,4"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--frames"), "{}", String::from_utf8_lossy(&o.stderr));
}
