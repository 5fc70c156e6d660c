//! FISTA (Beck & Teboulle 2009) for `min_x f(x) + g(x)` with a smooth `f` (gradient Lipschitz
//! constant `L`) and a `g` with a computable prox: the one accelerated proximal-gradient loop
//! of the crate (the joint kernel refinement and the diagnosis' kernel fit).
//!
//! ```text
//! x⁺ = prox_{g/L}(z − ∇f(z) / L)
//! t⁺ = (1 + √(1 + 4t²)) / 2,   z ← x⁺ + ((t − 1)/t⁺)(x⁺ − x),   x ← x⁺
//! ```
//!
//! The loop owns the iteration caps and the stopping rules, each an option so every caller
//! keeps its behaviour: adaptive restart of the momentum when the step goes against the
//! gradient mapping (`⟨z − x⁺, x⁺ − x⟩ > 0`, O'Donoghue & Candès 2015), a relative-step
//! tolerance `‖x⁺ − x‖/‖x⁺‖`, and a stall rule on `f` (the objective at `z` fell by less than a
//! fraction over a window of iterations). `on_iteration(iteration, relative_step)` is called
//! after every iteration (progress); returning `false` cancels. Norms accumulate in `f64`.

use super::primal_dual::Stats;

/// A composite problem `f + g` for [`fista`].
pub trait Composite {
    /// `out = ∇f(x)`; returns `f(x)`.
    fn gradient(&mut self, x: &[f32], out: &mut [f32]) -> f64;
    /// `x = prox_{g/l}(v)`, the prox with step `1/l`.
    fn prox(&mut self, l: f32, v: &[f32], x: &mut [f32]);
}

/// The stall rule: stop when `f` fell by less than `decrease · f` over the last `window`
/// iterations.
#[derive(Clone, Copy, Debug)]
pub struct Stall {
    pub window: usize,
    pub decrease: f64,
}

/// Settings of [`fista`].
#[derive(Clone, Debug)]
pub struct FistaOptions {
    pub max_iterations: usize,
    /// No stopping rule applies before this many iterations (`usize::MAX`: run to the cap).
    pub min_iterations: usize,
    /// Stop at a relative step below this.
    pub tolerance: f64,
    /// Adaptive restart of the momentum.
    pub restart: bool,
    pub stall: Option<Stall>,
}

/// FISTA's state between two runs on (nearly) the same problem: the extrapolation as an
/// offset from the last iterate (`z − x`; the loop's `x_prev` equals `x` between iterations)
/// and `t`, so that a later run continues the acceleration instead of starting again from
/// `z = x, t = 1` ([`fista_resume`]).
#[derive(Clone, Debug, Default)]
pub struct Momentum {
    /// `z − x` after the last iteration.
    pub ahead: Vec<f32>,
    pub t: f64,
}

/// Runs FISTA from `x` (updated in place) with the Lipschitz constant `l` of `∇f`.
/// `Stats::primal_objective` is `f` at the last extrapolated point; `criterion` the last
/// relative step.
pub fn fista<P: Composite + ?Sized>(p: &mut P, x: &mut [f32], opts: &FistaOptions, l: f32, on_iteration: impl FnMut(usize, f64) -> bool) -> Stats {
    fista_resume(p, x, &mut Momentum::default(), 1.0, opts, l, on_iteration)
}

/// [`fista`] continuing `momentum` (when its length matches `x`; else from `t = 1`), its
/// offsets scaled by `scale` (the caller's rescaling of `x` since the last run); leaves the
/// final momentum in it.
pub fn fista_resume<P: Composite + ?Sized>(p: &mut P, x: &mut [f32], momentum: &mut Momentum, scale: f32, opts: &FistaOptions, l: f32, mut on_iteration: impl FnMut(usize, f64) -> bool) -> Stats {
    let n = x.len();
    let mut z = x.to_vec();
    let mut x_prev = x.to_vec();
    let mut t = 1.0f64;
    if momentum.ahead.len() == n {
        z.iter_mut().zip(&momentum.ahead).for_each(|(zi, a)| *zi += scale * a);
        t = momentum.t;
    }
    let mut g = vec![0.0f32; n];
    let mut v = vec![0.0f32; n];
    let mut stats = Stats::default();
    let mut history = Vec::with_capacity(opts.max_iterations.min(1 << 16));
    for it in 1..=opts.max_iterations {
        stats.primal_objective = p.gradient(&z, &mut g);
        history.push(stats.primal_objective);
        for ((vi, &zi), &gi) in v.iter_mut().zip(&z).zip(&g) {
            *vi = zi - gi / l;
        }
        p.prox(l, &v, x);
        let (mut dx2, mut x2, mut dot) = (0.0f64, 0.0f64, 0.0f64);
        for i in 0..n {
            let dx = (x[i] - x_prev[i]) as f64;
            dx2 += dx * dx;
            x2 += (x[i] as f64) * (x[i] as f64);
            dot += (z[i] - x[i]) as f64 * dx;
        }
        if opts.restart && dot > 0.0 {
            t = 1.0;
        }
        let t_new = 0.5 * (1.0 + (1.0 + 4.0 * t * t).sqrt());
        let beta = ((t - 1.0) / t_new) as f32;
        for i in 0..n {
            z[i] = x[i] + beta * (x[i] - x_prev[i]);
        }
        x_prev.copy_from_slice(x);
        t = t_new;
        stats.iterations = it;
        let crit = (dx2 / x2.max(1e-300)).sqrt();
        stats.criterion = crit;
        if !on_iteration(it, crit) {
            break;
        }
        let stalled = opts.stall.is_some_and(|s| it > s.window && history[it - 1 - s.window] - history[it - 1] < s.decrease * history[it - 1]);
        if it >= opts.min_iterations && (crit < opts.tolerance || stalled) {
            stats.converged = true;
            break;
        }
    }
    momentum.ahead = z.iter().zip(x.iter()).map(|(a, b)| a - b).collect();
    momentum.t = t;
    stats
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::prox::project_simplex;

    /// `½‖D(x − c)‖²` over the simplex, `D` diagonal and ill-conditioned; the solution is known.
    struct Quadratic {
        d: Vec<f32>,
        c: Vec<f32>,
    }

    impl Composite for Quadratic {
        fn gradient(&mut self, x: &[f32], out: &mut [f32]) -> f64 {
            let mut f = 0.0;
            for i in 0..x.len() {
                let r = x[i] - self.c[i];
                out[i] = self.d[i] * r;
                f += 0.5 * (self.d[i] * r * r) as f64;
            }
            f
        }
        fn prox(&mut self, _l: f32, v: &[f32], x: &mut [f32]) {
            x.copy_from_slice(v);
            project_simplex(x, 1.0);
        }
    }

    fn problem() -> Quadratic {
        // the unconstrained minimiser (0.7, 0.5, −0.2) is off the simplex; the solution of the
        // equal-weight case is the projection (0.6, 0.4, 0)
        Quadratic { d: vec![1.0, 1.0, 1.0], c: vec![0.7, 0.5, -0.2] }
    }

    #[test]
    fn converges_with_and_without_restart() {
        for restart in [false, true] {
            let mut p = problem();
            let mut x = vec![1.0 / 3.0; 3];
            let o = FistaOptions { max_iterations: 500, min_iterations: 1, tolerance: 1e-7, restart, stall: None };
            let st = fista(&mut p, &mut x, &o, 1.0, |_, _| true);
            assert!(st.converged, "{st:?}");
            for (a, b) in x.iter().zip([0.6, 0.4, 0.0]) {
                assert!((a - b).abs() < 1e-5, "restart {restart}: {x:?}");
            }
        }
    }

    /// Restart speeds up an ill-conditioned problem; the stall rule stops a slow one early;
    /// `min_iterations = usize::MAX` runs to the cap; the callback cancels.
    #[test]
    fn options_change_the_run() {
        let ill = || Quadratic { d: vec![1.0, 1e-3, 0.5, 1e-2], c: vec![0.9, 0.05, 0.3, -0.4] };
        let run = |restart: bool, stall: Option<Stall>, min: usize| {
            let mut p = ill();
            let mut x = vec![0.25; 4];
            let o = FistaOptions { max_iterations: 3000, min_iterations: min, tolerance: 1e-9, restart, stall };
            fista(&mut p, &mut x, &o, 1.0, |_, _| true).iterations
        };
        let (plain, restarted) = (run(false, None, 1), run(true, None, 1));
        assert!(restarted < plain, "restart {restarted} vs plain {plain}");
        let stalled = run(true, Some(Stall { window: 5, decrease: 1e-3 }), 1);
        assert!(stalled < restarted, "stall {stalled} vs {restarted}");
        assert_eq!(run(false, None, usize::MAX), 3000);
        let mut p = ill();
        let mut x = vec![0.25; 4];
        let o = FistaOptions { max_iterations: 100, min_iterations: 1, tolerance: 0.0, restart: true, stall: None };
        assert_eq!(fista(&mut p, &mut x, &o, 1.0, |it, _| it < 7).iterations, 7);
    }

    /// [`fista_resume`]: two runs of `k` iterations with the momentum handed on are one run of
    /// `2k` (bit for bit, with and without restart); the second run started afresh (`t = 1`,
    /// `z = x`, what [`fista`] does) is not, and ends farther from the solution on an
    /// ill-conditioned problem. A scale applies to the handed-on offsets.
    #[test]
    fn resumed_momentum_continues_the_run() {
        // the solution `c` inside the simplex: the slow directions keep moving for hundreds of
        // iterations
        let ill = || Quadratic { d: vec![1.0, 1e-3, 2e-3, 5e-3], c: vec![0.1, 0.2, 0.3, 0.4] };
        let start = vec![0.7f32, 0.1, 0.1, 0.1];
        for restart in [false, true] {
            let o = |n| FistaOptions { max_iterations: n, min_iterations: usize::MAX, tolerance: 0.0, restart, stall: None };
            let mut whole = start.clone();
            fista(&mut ill(), &mut whole, &o(60), 1.0, |_, _| true);
            let mut x = start.clone();
            let mut m = Momentum::default();
            fista_resume(&mut ill(), &mut x, &mut m, 1.0, &o(30), 1.0, |_, _| true);
            let mut fresh = x.clone();
            fista_resume(&mut ill(), &mut x, &mut m, 1.0, &o(30), 1.0, |_, _| true);
            assert_eq!(x, whole, "restart {restart}");
            fista(&mut ill(), &mut fresh, &o(30), 1.0, |_, _| true);
            assert_ne!(fresh, whole, "restart {restart}");
            let f = |v: &[f32]| {
                let mut g = vec![0.0; 4];
                ill().gradient(v, &mut g)
            };
            assert!(f(&x) < f(&fresh), "restart {restart}: resumed {} vs fresh {}", f(&x), f(&fresh));
        }
        let mut m = Momentum { ahead: vec![0.1, -0.1, 0.0, 0.0], t: 3.0 };
        let mut x = vec![0.25f32; 4];
        let o = FistaOptions { max_iterations: 0, min_iterations: usize::MAX, tolerance: 0.0, restart: true, stall: None };
        fista_resume(&mut ill(), &mut x, &mut m, 2.0, &o, 1.0, |_, _| true);
        for (a, b) in m.ahead.iter().zip([0.2, -0.2, 0.0, 0.0]) {
            assert!((a - b).abs() < 1e-6, "{:?}", m.ahead);
        }
    }
}
