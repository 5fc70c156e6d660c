//! Flags shared by several commands, resolved into the library's option types.

use clap::Args;
use lensrig::estimate::EstimateOptions;
use std::path::PathBuf;

/// The estimation flags of `estimate`, `demo`, `bench`, `calibrate` and `diagnose`
/// (flattened into each; a command may change a default with `mut_arg`). Sizes in pixels.
#[derive(Args, Debug, Clone)]
pub struct EstimateArgs {
    /// Kernel size (odd, pixels); default: measured from the data (demo and mock rigs: the
    /// simulator's suggestion).
    #[arg(long)]
    pub kernel: Option<usize>,
    /// Spacing of the PSF centres in pixels; default: from how fast the PSF changes across the
    /// field (between 1.8 kernels and half the shorter side; each centre is fitted on a window
    /// of about four kernels, then all kernels jointly).
    #[arg(long)]
    pub tile: Option<usize>,
    /// Fit window side around each PSF centre; default: chosen by `estimate`.
    #[arg(long)]
    pub window: Option<usize>,
    /// Multiplier of the automatic TV weight.
    #[arg(long, default_value_t = 1.0)]
    pub lambda_scale: f64,
    /// Iterations of each window's fit (at most).
    #[arg(long, default_value_t = 150)]
    pub max_iterations: usize,
    /// Relative step at which a window's iterations stop.
    #[arg(long, default_value_t = 1e-3)]
    pub tolerance: f64,
    /// Iterations of the joint refinement of all kernels with the interpolated forward model
    /// (at most; it stops when χ² stalls); 0 keeps the per-window fits.
    #[arg(long, default_value_t = EstimateOptions::default().joint_iterations)]
    pub joint_iterations: usize,
    /// Keep the rule's TV weight in the joint refinement instead of choosing its multiplier
    /// (×0.5, ×1, ×2) per channel on held-out pixels.
    #[arg(long)]
    pub fixed_lambda: bool,
}

impl EstimateArgs {
    /// The estimation options these flags select (everything else at its default).
    pub fn options(&self) -> EstimateOptions {
        EstimateOptions {
            kernel_size: self.kernel,
            tile: self.tile,
            window: self.window,
            lambda_scale: self.lambda_scale,
            max_iterations: self.max_iterations,
            tolerance: self.tolerance,
            joint_iterations: self.joint_iterations,
            select_lambda: !self.fixed_lambda,
            ..Default::default()
        }
    }
}

/// The rig flags of `capture` and `calibrate`.
#[derive(Args, Debug, Clone)]
pub struct RigArgs {
    /// Rig config (TOML), e.g. rig-configs/mock.toml.
    #[arg(long)]
    pub rig: PathBuf,
    /// Serial port of the controller, overriding the config.
    #[arg(long)]
    pub port: Option<PathBuf>,
    /// Continue an interrupted session after its last finished pair.
    #[arg(long)]
    pub resume: bool,
}

#[cfg(test)]
mod tests {
    use crate::cli::{Cli, Command};
    use clap::Parser;

    fn parse(args: &[&str]) -> Command {
        match Cli::try_parse_from(std::iter::once("lensrig").chain(args.iter().copied())) {
            Ok(c) => c.command,
            Err(e) => panic!("{args:?}: {e}"),
        }
    }

    /// The shared flags keep each command's former defaults: calibrate fits windows with 300
    /// iterations, diagnose's base estimate has no joint refinement, the others 150 and 32.
    #[test]
    fn each_command_keeps_its_estimation_defaults() {
        let Command::Calibrate(c) = parse(&["calibrate", "--rig", "r.toml", "--out", "o"]) else { panic!("calibrate") };
        assert_eq!((c.estimation.max_iterations, c.estimation.joint_iterations), (300, 32));
        let Command::Diagnose(d) = parse(&["diagnose", "--open", "a", "--pinhole", "b", "--out", "o"]) else { panic!("diagnose") };
        let o = d.options().estimate;
        assert_eq!((o.max_iterations, o.joint_iterations, o.kernel_size), (150, 0, None));
        let Command::Estimate(e) = parse(&["estimate", "--open", "a", "--pinhole", "b", "--out", "o", "--kernel", "21", "--black-level", "0.0625"]) else { panic!("estimate") };
        let o = e.options();
        assert_eq!((o.max_iterations, o.joint_iterations, o.kernel_size, o.black_level.clone(), o.tolerance, o.lambda_scale), (150, 32, Some(21), vec![0.0625], 1e-3, 1.0));
        let Command::Demo(m) = parse(&["demo", "--out", "o", "--joint-iterations", "0"]) else { panic!("demo") };
        assert_eq!((m.estimation.options().joint_iterations, m.estimation.options().max_iterations), (0, 150));
    }

    /// `deblur --law-weighted-data` switches the variance-weighted data term on; it is off by default.
    #[test]
    fn deblur_law_weighted_data_is_opt_in() {
        let base = ["deblur", "--profile", "p", "--in", "a.png", "--out", "b.png"];
        let Command::Deblur(d) = parse(&base) else { panic!("deblur") };
        assert!(!d.options().law_data_weight);
        let with: Vec<&str> = base.iter().copied().chain(["--law-weighted-data"]).collect();
        let Command::Deblur(d) = parse(&with) else { panic!("deblur") };
        assert!(d.options().law_data_weight);
    }

    /// `deblur --texture-return` switches the texture-return step on; it is off by default.
    #[test]
    fn deblur_texture_return_is_opt_in() {
        let base = ["deblur", "--profile", "p", "--in", "a.png", "--out", "b.png"];
        let Command::Deblur(d) = parse(&base) else { panic!("deblur") };
        assert!(!d.options().texture_return);
        let with: Vec<&str> = base.iter().copied().chain(["--texture-return"]).collect();
        let Command::Deblur(d) = parse(&with) else { panic!("deblur") };
        assert!(d.options().texture_return);
    }
}
