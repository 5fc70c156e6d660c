//! Backward elimination after the effect search: an effect accepted early can be made
//! redundant by one accepted later (a halo as wide as the field is an offset plus a gain, so
//! `veiling_glare` can win a round that `black_level` then takes over). With two or more effects
//! in the model, each *removable* one is taken out in turn and the rest refitted with the
//! candidates' budget, against a null refit of the full model with the same budget; an effect
//! that would no longer be accepted — its removal raises `χ² + χ²_noise-law` by less than
//! [`super::DiagnoseOptions::min_gain`] of the null refit's, or lowers BIC — is dropped (the one
//! that costs least first), and the test repeats.
//!
//! Removable effects are the scalar terms the kernels need no re-initialisation for:
//! `vignetting`, `illumination_gradient`, `black_level`, `veiling_glare` (the offset or the
//! exposure ratio take back what they held within one Gauss–Newton step). Effects that move
//! the geometry or the kernels (`misregistration`, `target_tilt`, `psf_field_variation`,
//! `pinhole_diffraction`, `tone_curve`, `saturation`) stay: a short refit without them would
//! start from kernels fitted to them and score them unfairly.
//!
//! The glare's width is searched, not fitted (`candidates::glare_sigma`): where the model
//! holds a `veiling_glare`, the width is searched again for the null refit and for each model
//! without an effect before its refit, so that each is scored at its best width. A wide
//! halo and a vignetting can stand in for a narrower halo: veiling glare + tone curve through
//! the sf11 design (1024×768, seed 74) ended at the floor with a halo of 303 px and a
//! vignetting against 76 px and none rendered.

use super::fit::{screen as fit, Data, Fit};
use super::model::Corrections;
use super::DiagnoseOptions;

/// The effects [`weakest_redundant`] may remove.
pub const REMOVABLE: [&str; 4] = ["vignetting", "illumination_gradient", "black_level", "veiling_glare"];

/// `c` without the effect `name` (one of [`REMOVABLE`]; other names leave `c` unchanged).
pub fn without(c: &Corrections, name: &str) -> Corrections {
    let mut out = c.clone();
    match name {
        "vignetting" => out.vignetting = None,
        "illumination_gradient" => out.illumination_gradient = None,
        "black_level" => out.black_level = None,
        "veiling_glare" => out.veiling_glare = None,
        _ => {}
    }
    out
}

/// `c` with its glare's width (if it has a glare) searched again on `current`'s kernels
/// ([`super::candidates::glare_sigma_of`]), its fraction kept (the refit fits it).
fn with_searched_glare(data: &Data, mut c: Corrections, current: &Fit) -> Corrections {
    if let Some(g) = c.veiling_glare {
        if let Some(sigma) = super::candidates::glare_sigma_of(data, &c, &current.model) {
            c.veiling_glare = Some(super::model::GlareCorrection { sigma_px: sigma, ..g });
        }
    }
    c
}

/// The removable effect of `current` that the search would no longer accept (module docs),
/// the one whose removal costs least, with the refit without it; `None` when every effect
/// still earns its place or the model has fewer than two effects.
pub fn weakest_redundant(data: &Data, current: &Fit, opts: &DiagnoseOptions) -> Option<(&'static str, Fit)> {
    let names = current.model.corrections.names();
    if names.len() < 2 {
        return None;
    }
    let mut null = fit(data, &with_searched_glare(data, current.model.corrections.clone(), current), &current.model, opts.candidate_fit);
    null.inherit_dof(current);
    let total = |f: &Fit| f.chi2() + f.noise_chi2;
    let mut best: Option<(&'static str, Fit, f64)> = None;
    for name in names.into_iter().filter(|n| REMOVABLE.contains(n)) {
        let c = with_searched_glare(data, without(&current.model.corrections, name), current);
        let mut f = fit(data, &c, &current.model, opts.candidate_fit);
        f.inherit_dof(current);
        // what the effect still removes, given the others
        let cost = (total(&f) - total(&null)) / total(&null).max(1e-300);
        let still_accepted = null.bic() < f.bic() && cost >= opts.min_gain;
        if !still_accepted && best.as_ref().map_or(true, |b| cost < b.2) {
            best = Some((name, f, cost));
        }
    }
    best.map(|(n, f, _)| (n, f))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnose::model::{BlackLevelCorrection, GlareCorrection, VignettingCorrection};

    #[test]
    fn without_removes_only_the_named_scalar_effect() {
        let c = Corrections {
            vignetting: Some(VignettingCorrection { k1: -0.2, k2: 0.0, k3: 0.0 }),
            black_level: Some(BlackLevelCorrection { offset: vec![0.01] }),
            veiling_glare: Some(GlareCorrection { fraction: 0.05, sigma_px: 30.0 }),
            target_tilt: Some(crate::diagnose::model::TiltCorrection { g: 1e-4, h: 0.0 }),
            ..Default::default()
        };
        assert_eq!(without(&c, "veiling_glare").names(), vec!["target_tilt", "veiling_glare", "vignetting", "black_level"].into_iter().filter(|n| *n != "veiling_glare").collect::<Vec<_>>());
        assert_eq!(without(&c, "target_tilt"), c, "geometry effects are not removable");
        for n in REMOVABLE {
            assert!(!without(&c, n).names().contains(&n));
        }
    }
}
