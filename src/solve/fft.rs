//! Two-dimensional real FFTs, planned once per size and shared.
//!
//! # Conventions
//! - Input planes are row-major `height × width` real arrays (see [`crate::image`]).
//! - Spectra hold the non-redundant half: `width / 2 + 1` frequencies along x, all `height`
//!   along y, stored **column-major**: bin `(kx, ky)` is `spec[kx * height + ky]`. Only
//!   pointwise products of spectra of the same plan are meaningful, so the layout never leaks.
//! - [`Fft2::forward`] is unnormalised; [`Fft2::inverse`] divides by `width * height`, so
//!   `inverse(forward(x)) == x`.
//! - Scratch: the `*_with` methods take caller-owned [`FftScratch`]; the plain methods use a
//!   per-thread cached scratch, so no transform allocates after warm-up.
//! - Plans come from a process-wide cache ([`Fft2::plan`]); sizes are best chosen with
//!   [`good_size`] (even, of the form 2^a·3^b), or [`fast_size`] (a multiple of 8 of that form)
//!   where a transform runs hundreds of times per product.

use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use rustfft::num_complex::Complex32;
use rustfft::{Fft, FftPlanner};
use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

/// A planned 2-D real FFT of one size.
pub struct Fft2 {
    pub width: usize,
    pub height: usize,
    /// `width / 2 + 1`
    pub half_width: usize,
    r2c: Arc<dyn RealToComplex<f32>>,
    c2r: Arc<dyn ComplexToReal<f32>>,
    col_fwd: Arc<dyn Fft<f32>>,
    col_inv: Arc<dyn Fft<f32>>,
}

impl std::fmt::Debug for Fft2 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Fft2({}x{})", self.width, self.height)
    }
}

type PlanCache = Mutex<HashMap<(usize, usize), Arc<Fft2>>>;

fn cache() -> &'static PlanCache {
    static CACHE: OnceLock<PlanCache> = OnceLock::new();
    CACHE.get_or_init(|| Mutex::new(HashMap::new()))
}

impl Fft2 {
    /// The shared plan for `width × height` (created on first use).
    pub fn plan(width: usize, height: usize) -> Arc<Fft2> {
        let mut c = cache().lock().unwrap_or_else(|e| e.into_inner());
        c.entry((width, height)).or_insert_with(|| Arc::new(Fft2::new(width, height))).clone()
    }

    fn new(width: usize, height: usize) -> Self {
        assert!(width > 0 && height > 0, "empty FFT");
        let mut rp = RealFftPlanner::<f32>::new();
        let mut cp = FftPlanner::<f32>::new();
        Self {
            width,
            height,
            half_width: width / 2 + 1,
            r2c: rp.plan_fft_forward(width),
            c2r: rp.plan_fft_inverse(width),
            col_fwd: cp.plan_fft_forward(height),
            col_inv: cp.plan_fft_inverse(height),
        }
    }

    /// Number of complex bins in a spectrum of this plan.
    pub fn spectrum_len(&self) -> usize {
        self.half_width * self.height
    }

    /// Caller-owned scratch buffers for the `*_with` transforms of this plan.
    pub fn make_scratch(&self) -> FftScratch {
        FftScratch {
            size: (self.width, self.height),
            row_real: self.r2c.make_input_vec(),
            r2c: self.r2c.make_scratch_vec(),
            c2r: self.c2r.make_scratch_vec(),
            col: vec![Complex32::new(0.0, 0.0); self.col_fwd.get_inplace_scratch_len().max(self.col_inv.get_inplace_scratch_len())],
            batch: vec![Complex32::new(0.0, 0.0); ROW_BATCH * self.half_width],
        }
    }

    /// Runs `f` with this thread's cached scratch for this plan (no allocation after the first
    /// call on a thread).
    fn with_cached_scratch<R>(&self, f: impl FnOnce(&mut FftScratch) -> R) -> R {
        thread_local! {
            static SCRATCH: std::cell::RefCell<Vec<FftScratch>> = const { std::cell::RefCell::new(Vec::new()) };
        }
        let key = (self.width, self.height);
        with_thread_cached(&SCRATCH, 8, |s| s.size == key, || self.make_scratch(), f)
    }

    /// Forward transform of a row-major real array of `width * height` values.
    pub fn forward(&self, input: &[f32]) -> Vec<Complex32> {
        let mut spec = vec![Complex32::new(0.0, 0.0); self.spectrum_len()];
        self.forward_into(input, &mut spec);
        spec
    }

    /// Forward transform into a caller-owned spectrum buffer.
    pub fn forward_into(&self, input: &[f32], spec: &mut [Complex32]) {
        self.with_cached_scratch(|s| self.forward_with(input, spec, s));
    }

    /// Forward transform with caller-owned scratch.
    pub fn forward_with(&self, input: &[f32], spec: &mut [Complex32], s: &mut FftScratch) {
        self.forward_rows_with(input, spec, |_| true, s)
    }

    /// Forward transform with caller-owned scratch, reading only the input rows `y` for which
    /// `rows(y)` is true: the other rows are taken as zero whatever `input` holds there (the
    /// caller need not clear them).
    pub fn forward_rows_with(&self, input: &[f32], spec: &mut [Complex32], rows: impl Fn(usize) -> bool, s: &mut FftScratch) {
        assert_eq!(input.len(), self.width * self.height, "FFT input size");
        self.forward_row_pass_with(input, self.height, spec, rows, s);
        self.col_fwd.process_with_scratch(spec, &mut s.col);
    }

    /// The row pass of the forward transform alone, on `n` rows (`input` row-major
    /// `n × width`, rows where `rows(y)` is false taken as zero): row `y`'s bin `kx` goes to
    /// `out[kx * n + y]` (column-major, columns of length `n`, unnormalised). With `n = height`
    /// and [`Fft2::forward_columns_with`] it is [`Fft2::forward_rows_with`]; in between, a
    /// factor that depends on `y` alone may be applied (separable weights,
    /// [`crate::optics::kernel_operator`]).
    pub fn forward_row_pass_with(&self, input: &[f32], n: usize, out: &mut [Complex32], rows: impl Fn(usize) -> bool, s: &mut FftScratch) {
        assert_eq!(input.len(), self.width * n, "FFT row-pass input size");
        assert_eq!(out.len(), self.half_width * n, "FFT row-pass output size");
        assert_eq!(s.size, (self.width, self.height), "FFT scratch size");
        let (w, hw) = (self.width, self.half_width);
        let zero = Complex32::new(0.0, 0.0);
        if (0..n).any(|y| !rows(y)) {
            out.fill(zero);
        }
        // rows in batches, so the transposed writes go out ROW_BATCH bins at a time
        let mut y0 = 0;
        while y0 < n {
            let nb = ROW_BATCH.min(n - y0);
            if (y0..y0 + nb).all(|y| !rows(y)) {
                y0 += nb;
                continue;
            }
            for j in 0..nb {
                let src = &input[(y0 + j) * w..(y0 + j + 1) * w];
                let dst = &mut s.batch[j * hw..(j + 1) * hw];
                if !rows(y0 + j) {
                    dst.fill(zero);
                    continue;
                }
                s.row_real.copy_from_slice(src);
                // Lengths are right by construction; realfft only errs on wrong lengths.
                let _ = self.r2c.process_with_scratch(&mut s.row_real, dst, &mut s.r2c);
            }
            for kx in 0..hw {
                let col = &mut out[kx * n + y0..kx * n + y0 + nb];
                for (j, c) in col.iter_mut().enumerate() {
                    *c = s.batch[j * hw + kx];
                }
            }
            y0 += nb;
        }
    }

    /// The column pass of the forward transform alone, in place on a column-major spectrum
    /// whose columns hold the row transforms ([`Fft2::forward_row_pass_with`], `n = height`).
    pub fn forward_columns_with(&self, spec: &mut [Complex32], s: &mut FftScratch) {
        assert_eq!(spec.len(), self.spectrum_len(), "FFT spectrum size");
        self.col_fwd.process_with_scratch(spec, &mut s.col);
    }

    /// The column pass of the inverse transform alone, in place on a column-major spectrum
    /// (unnormalised): bin `kx * height + y` then holds row `y`'s half spectrum, and a factor
    /// that depends on `y` alone may be applied before [`Fft2::inverse_row_pass_with`].
    pub fn inverse_columns_with(&self, spec: &mut [Complex32], s: &mut FftScratch) {
        assert_eq!(spec.len(), self.spectrum_len(), "FFT spectrum size");
        self.col_inv.process_with_scratch(spec, &mut s.col);
    }

    /// Inverse transform (normalised by `1 / (width * height)`); consumes the spectrum.
    pub fn inverse(&self, mut spec: Vec<Complex32>) -> Vec<f32> {
        let mut out = vec![0.0; self.width * self.height];
        self.inverse_into(&mut spec, &mut out);
        out
    }

    /// Inverse transform into `out`; `spec` is used as scratch and left modified.
    pub fn inverse_into(&self, spec: &mut [Complex32], out: &mut [f32]) {
        self.with_cached_scratch(|s| self.inverse_rows_with(spec, out, |_| true, s));
    }

    /// Inverse transform with caller-owned scratch, computing only the output rows `y` for
    /// which `rows(y)` is true (the other rows of `out` are left untouched); `spec` is used as
    /// scratch and left modified.
    pub fn inverse_rows_with(&self, spec: &mut [Complex32], out: &mut [f32], rows: impl Fn(usize) -> bool, s: &mut FftScratch) {
        assert_eq!(spec.len(), self.spectrum_len(), "FFT spectrum size");
        self.col_inv.process_with_scratch(spec, &mut s.col);
        self.inverse_row_pass_with(spec, self.height, out, rows, s);
    }

    /// The row pass of the inverse transform alone, on `n` rows: `spec` column-major with
    /// columns of length `n` (bin `kx` of row `y` at `kx * n + y`, after
    /// [`Fft2::inverse_columns_with`] or a weighted sum of such), `out` row-major `n × width`,
    /// normalised by `1 / (width * height)` like [`Fft2::inverse`]; only the rows where
    /// `rows(y)` is true are written.
    pub fn inverse_row_pass_with(&self, spec: &[Complex32], n: usize, out: &mut [f32], rows: impl Fn(usize) -> bool, s: &mut FftScratch) {
        assert_eq!(out.len(), self.width * n, "FFT row-pass output size");
        assert_eq!(spec.len(), self.half_width * n, "FFT row-pass input size");
        assert_eq!(s.size, (self.width, self.height), "FFT scratch size");
        let (w, hw) = (self.width, self.half_width);
        let norm = 1.0 / (w * self.height) as f32;
        let mut res = std::mem::take(&mut s.row_real);
        let mut ys = [0usize; ROW_BATCH];
        let mut y = 0;
        while y < n {
            // gather the next batch of requested rows
            let mut nb = 0;
            while y < n && nb < ROW_BATCH {
                if rows(y) {
                    ys[nb] = y;
                    nb += 1;
                }
                y += 1;
            }
            for kx in 0..hw {
                let col = &spec[kx * n..(kx + 1) * n];
                for (j, &yy) in ys[..nb].iter().enumerate() {
                    s.batch[j * hw + kx] = col[yy];
                }
            }
            for (j, &yy) in ys[..nb].iter().enumerate() {
                let row = &mut s.batch[j * hw..(j + 1) * hw];
                // DC and (for even widths) Nyquist bins of a real signal's row transform are real.
                row[0].im = 0.0;
                if w % 2 == 0 {
                    row[hw - 1].im = 0.0;
                }
                let _ = self.c2r.process_with_scratch(row, &mut res, &mut s.c2r);
                for (o, r) in out[yy * w..(yy + 1) * w].iter_mut().zip(&res) {
                    *o = r * norm;
                }
            }
        }
        s.row_real = res;
    }

    /// Spatial frequencies (cycles per pixel) of bin `i` of a spectrum: `(fx, fy)`.
    pub fn frequency(&self, i: usize) -> (f32, f32) {
        let kx = i / self.height;
        let ky = i % self.height;
        let fy = if ky <= self.height / 2 { ky as f32 } else { ky as f32 - self.height as f32 };
        (kx as f32 / self.width as f32, fy / self.height as f32)
    }
}

/// Scratch buffers for one plan size ([`Fft2::make_scratch`]); reuse it across calls.
pub struct FftScratch {
    size: (usize, usize),
    row_real: Vec<f32>,
    r2c: Vec<Complex32>,
    c2r: Vec<Complex32>,
    col: Vec<Complex32>,
    batch: Vec<Complex32>,
}

/// Rows transformed together before their bins are transposed into the column-major spectrum.
const ROW_BATCH: usize = 32;

/// The smallest even `m >= n` of the form 2^a·3^b (fast for rustfft and realfft).
pub fn good_size(n: usize) -> usize {
    smallest_2a3b(n, 2)
}

/// The smallest `m >= max(n, p)` of the form `2^a·3^b` with `2^a ≥ p` (`p` a power of 2).
fn smallest_2a3b(n: usize, p: usize) -> usize {
    let n = n.max(p);
    let mut best = usize::MAX;
    let mut p2 = p;
    while p2 < 2 * n + p {
        let mut v = p2;
        while v < n {
            v *= 3;
        }
        best = best.min(v);
        p2 *= 2;
    }
    best
}

/// The smallest `m >= n` of the form 2^a·3^b with `a ≥ 3` (a multiple of 8): the sizes whose
/// transforms rustfft runs fastest per element. [`good_size`] may return twice or four times a
/// power of 3 (54, 108, 162, 324, …), whose transforms cost 1.2–1.6× as much per element as
/// their neighbours: column passes measured on the host of session 24 (Intel Xeon, AVX-512; ns
/// per element of a pass) F = 72: 0.42, 96: 0.65, 128: 0.48, 144: 0.67, 162: 0.78, 192: 0.64,
/// 216: 0.71, 256: 0.53. The blocked kernel operator, which runs hundreds of passes per product,
/// takes its block size from this ([`crate::optics::kernel_operator`]): at 27-px kernels
/// [`good_size`] gave it F = 162 and a joint refinement 1.4× as slow as with [`fast_size`]'s
/// layout (11.1 s against 7.8 s on the achromat).
pub fn fast_size(n: usize) -> usize {
    debug_assert!(n <= 1 << 40, "FFT size {n} out of range");
    smallest_2a3b(n, 8)
}

/// Whether the hot complex multiply–accumulate loops around the FFTs (the blocked kernel
/// operator, [`crate::optics::kernel_operator`]; the window fit's normal operator,
/// [`crate::estimate::solver`]) run in their AVX2 build: on x86-64 CPUs with AVX2, detected
/// once. Those builds do the same operations in the same order (no fused multiply–add), so
/// they return the same bits as the baseline build. `LENSRIG_NO_AVX2` set in the environment
/// forces the baseline build (timing comparisons).
#[cfg(target_arch = "x86_64")]
pub fn has_avx2() -> bool {
    static AVX2: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *AVX2.get_or_init(|| std::env::var_os("LENSRIG_NO_AVX2").is_none() && std::is_x86_feature_detected!("avx2"))
}

/// Runs `f` on a value taken from a thread-local cache (the first that `fits`, else `make()`)
/// and puts it back afterwards, keeping at most `keep` values (oldest dropped first): per-thread
/// work buffers for FFT plans of a few sizes, without allocation after the first call.
pub(crate) fn with_thread_cached<T: 'static, R>(
    cache: &'static std::thread::LocalKey<std::cell::RefCell<Vec<T>>>,
    keep: usize,
    fits: impl Fn(&T) -> bool,
    make: impl FnOnce() -> T,
    f: impl FnOnce(&mut T) -> R,
) -> R {
    let taken = cache.with(|c| {
        let mut v = c.borrow_mut();
        v.iter().position(&fits).map(|i| v.swap_remove(i))
    });
    let mut item = taken.unwrap_or_else(make);
    let r = f(&mut item);
    cache.with(|c| {
        let mut v = c.borrow_mut();
        if v.len() >= keep {
            v.remove(0);
        }
        v.push(item);
    });
    r
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    #[cfg(target_arch = "x86_64")]
    /// Whether this CPU has AVX2, for the tests that compare the AVX2 builds of hot loops with
    /// the baseline ([`has_avx2`]); says so on stderr when it has not (nothing to compare).
    pub(crate) fn cpu_has_avx2() -> bool {
        let yes = std::is_x86_feature_detected!("avx2");
        if !yes {
            eprintln!("this CPU has no AVX2: nothing to compare");
        }
        yes
    }

    /// Whether `m` is of the form 2^a·3^b.
    fn is_2a3b(mut m: usize) -> bool {
        while m > 1 && m % 2 == 0 {
            m /= 2;
        }
        while m > 1 && m % 3 == 0 {
            m /= 3;
        }
        m == 1
    }

    #[test]
    fn good_sizes() {
        assert_eq!(good_size(1), 2);
        assert_eq!(good_size(100), 108);
        assert_eq!(good_size(256), 256);
        assert_eq!(good_size(257), 288);
        assert_eq!(good_size(318), 324);
        for n in 2..600 {
            let g = good_size(n);
            assert!(g >= n && g % 2 == 0);
            assert!(is_2a3b(g));
        }
    }

    #[test]
    fn fast_sizes_are_multiples_of_eight_of_the_form_2a_3b() {
        assert_eq!(fast_size(77), 96);
        assert_eq!(fast_size(72), 72);
        assert_eq!(fast_size(150), 192);
        assert_eq!(fast_size(1), 8);
        for n in 1..800 {
            let f = fast_size(n);
            assert!(f >= n && f % 8 == 0, "{n} -> {f}");
            assert!(is_2a3b(f), "{n} -> {f}");
            // the smallest such size
            assert!((n..f).all(|g| g % 8 != 0 || !is_2a3b(g)), "{n} -> {f}");
        }
    }

    #[test]
    fn round_trip_and_dft_oracle() {
        let (w, h) = (6, 5);
        let mut x: Vec<f32> = (0..w * h).map(|i| ((i * 37 % 11) as f32) - 3.0).collect();
        // one all-zero row exercises the skipped row transform
        x[2 * w..3 * w].iter_mut().for_each(|v| *v = 0.0);
        let f = Fft2::plan(w, h);
        let spec = f.forward(&x);
        // compare against a direct DFT
        for i in 0..spec.len() {
            let kx = i / h;
            let ky = i % h;
            let mut acc = Complex32::new(0.0, 0.0);
            for y in 0..h {
                for xx in 0..w {
                    let ph = -2.0 * std::f32::consts::PI * (kx as f32 * xx as f32 / w as f32 + ky as f32 * y as f32 / h as f32);
                    acc += Complex32::new(ph.cos(), ph.sin()) * x[y * w + xx];
                }
            }
            assert!((acc - spec[i]).norm() < 1e-3, "bin {kx},{ky}: {acc} vs {}", spec[i]);
        }
        let back = f.inverse(spec.clone());
        for (a, b) in x.iter().zip(&back) {
            assert!((a - b).abs() < 1e-4);
        }
        // partial inverse: only the requested rows, identical to the full one
        let mut s = f.make_scratch();
        let mut part = vec![f32::NAN; w * h];
        f.inverse_rows_with(&mut spec.clone(), &mut part, |y| y % 2 == 1, &mut s);
        for y in 0..h {
            for xx in 0..w {
                let v = part[y * w + xx];
                if y % 2 == 1 {
                    assert!((v - back[y * w + xx]).abs() < 1e-6);
                } else {
                    assert!(v.is_nan());
                }
            }
        }
    }

    /// The split passes compose to the full transforms, and a factor depending on `y` alone
    /// applied between them equals the transform of the row-weighted input (what the kernel
    /// operator's factored blocks rely on).
    #[test]
    fn split_passes_compose_and_commute_with_row_factors() {
        let (w, h) = (12, 10);
        let x: Vec<f32> = (0..w * h).map(|i| ((i * 37 % 23) as f32) / 7.0 - 1.5).collect();
        let a: Vec<f32> = (0..h).map(|y| 0.3 + 0.1 * y as f32).collect();
        let f = Fft2::plan(w, h);
        let mut s = f.make_scratch();
        let xa: Vec<f32> = x.iter().enumerate().map(|(i, v)| v * a[i / w]).collect();
        let full = f.forward(&xa);
        let mut split = vec![Complex32::new(0.0, 0.0); f.spectrum_len()];
        f.forward_row_pass_with(&x, h, &mut split, |_| true, &mut s);
        for col in split.chunks_exact_mut(h) {
            col.iter_mut().zip(&a).for_each(|(c, &q)| *c *= q);
        }
        f.forward_columns_with(&mut split, &mut s);
        let scale = full.iter().map(|c| c.norm()).fold(0.0f32, f32::max);
        for (p, q) in full.iter().zip(&split) {
            assert!((p - q).norm() <= 1e-5 * scale, "forward {p} vs {q}");
        }
        // inverse: columns, factor, rows == factor applied to the inverse's rows
        let mut spec = f.forward(&x);
        f.inverse_columns_with(&mut spec, &mut s);
        for col in spec.chunks_exact_mut(h) {
            col.iter_mut().zip(&a).for_each(|(c, &q)| *c *= q);
        }
        let mut back = vec![0.0f32; w * h];
        f.inverse_row_pass_with(&spec, h, &mut back, |_| true, &mut s);
        for (i, (v, b)) in x.iter().zip(&back).enumerate() {
            assert!((v * a[i / w] - b).abs() < 1e-5, "inverse {} vs {b}", v * a[i / w]);
        }
    }
}
