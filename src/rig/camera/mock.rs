//! [`MockCamera`]: a camera that renders the noise target through the simulated lens.
//!
//! The camera knows nothing about the capture plan. It reads the machine position from a
//! shared [`PositionSource`] that the capture loop updates from the controller's **status
//! reports** after every move, and maps it:
//!
//! - aperture axis position → f-number: log-linear between the config's `axes.aperture.open`
//!   (→ `lens.f_number_open`) and `axes.aperture.pinhole` (→ `lens.f_number_pinhole`), clamped;
//!   `lens.pinhole = "ideal"` makes the pinhole position a perfectly sharp reference.
//! - stage axis position → field offset: the target slides by `lens.cells_per_mm` noise cells
//!   per mm along x, so each stage position sees different noise.
//! - exposure (µs) and gain (dB) → linear exposure: white =
//!   `brightness · t[s] · 10^(gain/20) / N²` on the full-scale axis; Poisson–Gaussian noise
//!   (full well, read noise, both scaled by gain), clipping at full scale, 16-bit quantisation.
//!
//! `[lens]` keys (all optional): `f_number_open` (2.8), `f_number_pinhole` (22),
//! `pinhole` (`"f-number"` or `"ideal"`), `pixels_per_cell` (1.6), `cells_per_mm` (1.0),
//! `brightness` (300, full-scale per second at f/1), `full_well_e` (20000), `read_noise_e` (6),
//! `bands` (`"rgb"` or `"mono"`, default `"mono"`), `seed` (1), `vignetting` (`[k1, k2, k3]`,
//! lensfun's `pa` relative illumination applied to every frame, see
//! [`crate::optics::vignetting`]; default none), `distortion` (`[a, b, c]`, lensfun's `ptlens`
//! geometric distortion, see [`crate::optics::distortion`]: every frame shows the target
//! where the distorted lens puts it, both apertures alike; must be monotonic over the frame;
//! default none), and the fault
//! `timeout_after_captures` (a capture after that many returns [`CameraError::Timeout`]
//! after `camera.frame_timeout_ms`,
//! for resume tests; the environment variable `LENSRIG_MOCK_TIMEOUT_AFTER_CAPTURES` does the
//! same without changing the config; `LENSRIG_MOCK_PANIC_AFTER_CAPTURES` makes the capture after
//! that many *panic*, for the panic-consistency test). `focal_length_mm`, `pixel_pitch_um` are accepted and informational.
//!
//! The flat field: at the stage position of the plan's `[plan.flat]` step a diffuser fills the
//! view, so the camera sees a uniform white (reflectance 1) field, unblurred (a uniform field
//! is unchanged by any PSF), through the vignetting.
//!
//! The lens's PSFs are sampled on a 9 × 7 grid whose outer centres lie on the frame's edges
//! ([`crate::optics::psf_grid::PsfGrid::edge_centers`]) and blended between them, so the blur
//! keeps changing out to the corners as a lens's does. (A tile-centred grid holds every PSF
//! constant in its outer half tile: a band along the frame's edges where the rendered lens stopped
//! changing, which no real lens has.)
//!
//! Clean images are cached per (f-number, stage position), so repeated frames only redraw noise.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime};

use super::{Camera, CameraError, FourCc, Frame, FrameFormat, FrameMeta};
use crate::image::{Image, Plane, SampleFormat, Transfer};
use crate::optics::capture::{render, Sensor, Shot};
use crate::optics::lens::{mono_band, LensModel};
use crate::optics::distortion::PtLens;
use crate::optics::vignetting::PaVignetting;
use crate::rig::config::RigConfig;
use crate::rig::controller::{Axis, Position};
use crate::rng::Rng;
use crate::target::{render_noise_scene, render_noise_scene_mapped, TargetSpec};

/// The machine position as last reported by the controller.
pub type PositionSource = Arc<Mutex<Position>>;

/// Faults a test can inject (all default off).
#[derive(Debug, Default)]
pub struct CameraFaults {
    /// Every capture fails with [`CameraError::Timeout`].
    pub timeout: AtomicBool,
    /// One-shot counter: the next `n` frames are dropped by the "driver"; the camera records
    /// them as discarded and waits for replacements (documented recovery).
    pub drop_frames: AtomicUsize,
    /// When > 0: captures after this many succeeded time out (simulates a hang mid-session).
    pub timeout_after_captures: AtomicUsize,
    /// When > 0: the capture after this many succeeded panics (a bug mid-session; test-only).
    pub panic_after_captures: AtomicUsize,
    /// One-shot: the next capture stalls this long (ms). Longer than the camera's
    /// `frame_timeout_ms`, it waits the timeout and fails with [`CameraError::Timeout`];
    /// shorter, the capture is just late.
    pub stall_once_ms: AtomicU64,
    /// The next this-many captures see the light dimmed to 70 % (a passing cloud, a lamp
    /// flickering): an illumination drift.
    pub dim_captures: AtomicUsize,
}

/// The simulated optics and sensor a mock rig uses, from the config's `[lens]` table.
#[derive(Clone, Debug)]
pub struct MockOptics {
    pub lens: LensModel,
    pub f_number_open: f64,
    /// `None`: an ideal (perfectly sharp) pinhole reference.
    pub f_number_pinhole: Option<f64>,
    pub pixels_per_cell: f64,
    pub cells_per_mm: f64,
    pub brightness: f64,
    pub sensor: Sensor,
    pub seed: u64,
    pub aperture_axis: Axis,
    pub stage_axis: Axis,
    pub aperture_open: f64,
    pub aperture_pinhole: f64,
    /// Tile grid and kernel size the PSFs are rendered with.
    pub psf_columns: usize,
    pub psf_rows: usize,
    pub kernel_size: usize,
    /// `[lens] vignetting`: the lens's relative illumination (`None`: none).
    pub vignetting: Option<PaVignetting>,
    /// `[lens] distortion`: the lens's geometric distortion (`None`: none).
    pub distortion: Option<PtLens>,
    /// Stage position of the diffuser (`[plan.flat] stage_mm`).
    pub flat_stage_mm: Option<f64>,
}

/// The keys `[lens]` may hold (see the module docs).
const KNOWN: [&str; 15] = [
    "focal_length_mm",
    "pixel_pitch_um",
    "f_number_open",
    "f_number_pinhole",
    "pinhole",
    "pixels_per_cell",
    "cells_per_mm",
    "brightness",
    "full_well_e",
    "read_noise_e",
    "bands",
    "seed",
    "timeout_after_captures",
    "vignetting",
    "distortion",
];

/// `[lens] vignetting = [k1, k2, k3]` (lensfun `pa`; fewer than three = trailing zeros), checked
/// to keep `V` in `(0, 1.5]`.
fn parse_vignetting(t: &toml::Table) -> Result<Option<PaVignetting>, MockError> {
    Ok(match t.get("vignetting") {
        None => None,
        Some(toml::Value::Array(a)) if (1..=3).contains(&a.len()) => {
            let mut k = [0.0; 3];
            for (d, v) in k.iter_mut().zip(a) {
                *d = v.as_float().or_else(|| v.as_integer().map(|i| i as f64)).ok_or_else(|| MockError::WrongType { key: "vignetting".into(), expected: "numbers", got: v.to_string() })?;
            }
            let v = PaVignetting { k };
            v.check().map_err(|e| MockError::BadValue { key: "vignetting", problem: e.to_string() })?;
            Some(v)
        }
        Some(v) => return Err(MockError::WrongType { key: "vignetting".into(), expected: "[k1, k2, k3] (lensfun pa)", got: v.to_string() }),
    })
}

/// `[lens] distortion = [a, b, c]` (lensfun ptlens; fewer than three = trailing zeros),
/// checked to be monotonic over a `width × height` frame.
fn parse_distortion(t: &toml::Table, width: usize, height: usize) -> Result<Option<PtLens>, MockError> {
    Ok(match t.get("distortion") {
        None => None,
        Some(toml::Value::Array(a)) if (1..=3).contains(&a.len()) => {
            let mut k = [0.0; 3];
            for (d, v) in k.iter_mut().zip(a) {
                *d = v.as_float().or_else(|| v.as_integer().map(|i| i as f64)).ok_or_else(|| MockError::WrongType { key: "distortion".into(), expected: "numbers", got: v.to_string() })?;
            }
            let d = PtLens { a: k[0], b: k[1], c: k[2] };
            d.check(width, height).map_err(|e| MockError::BadValue { key: "distortion", problem: e.to_string() })?;
            Some(d)
        }
        Some(v) => return Err(MockError::WrongType { key: "distortion".into(), expected: "[a, b, c] (lensfun ptlens)", got: v.to_string() }),
    })
}

impl MockOptics {
    /// Reads `[lens]` (see the module docs).
    ///
    /// # Errors
    /// A key with the wrong type or an impossible value.
    pub fn from_config(cfg: &RigConfig) -> Result<Self, MockError> {
        let empty = toml::Table::new();
        let t = cfg.lens.as_ref().unwrap_or(&empty);
        let num = |k: &str, d: f64| -> Result<f64, MockError> {
            match t.get(k) {
                None => Ok(d),
                Some(toml::Value::Float(f)) => Ok(*f),
                Some(toml::Value::Integer(i)) => Ok(*i as f64),
                Some(v) => Err(MockError::WrongType { key: k.to_string(), expected: "a number", got: v.to_string() }),
            }
        };
        let s = |k: &str, d: &str| -> Result<String, MockError> {
            match t.get(k) {
                None => Ok(d.to_string()),
                Some(toml::Value::String(s)) => Ok(s.clone()),
                Some(v) => Err(MockError::WrongType { key: k.to_string(), expected: "a string", got: v.to_string() }),
            }
        };
        if let Some(k) = t.keys().find(|k| !KNOWN.contains(&k.as_str())) {
            return Err(MockError::UnknownKey { key: k.clone(), known: KNOWN.join(", ") });
        }
        let (w, h) = (cfg.camera.width as usize, cfg.camera.height as usize);
        let mut lens = LensModel::demo(w, h);
        match s("bands", "mono")?.as_str() {
            "mono" => lens.bands = mono_band(),
            "rgb" => {}
            o => return Err(MockError::BadValue { key: "bands", problem: format!("expected \"mono\" or \"rgb\", got {o:?}") }),
        }
        let f_open = num("f_number_open", 2.8)?;
        let f_pin = num("f_number_pinhole", 22.0)?;
        if !(f_open > 0.0 && f_pin > f_open) {
            return Err(MockError::FNumbers { open: f_open, pinhole: f_pin });
        }
        let pinhole = match s("pinhole", "f-number")?.as_str() {
            "ideal" => None,
            "f-number" => Some(f_pin),
            o => return Err(MockError::BadValue { key: "pinhole", problem: format!("expected \"f-number\" or \"ideal\", got {o:?}") }),
        };
        let ppc = num("pixels_per_cell", 1.6)?;
        if ppc <= 0.0 {
            return Err(MockError::BadValue { key: "pixels_per_cell", problem: "must be > 0".into() });
        }
        let sensor = Sensor { full_well_e: num("full_well_e", 20_000.0)?, read_noise_e: num("read_noise_e", 6.0)?, ..Sensor::default() };
        let kernel_size = lens.suggested_kernel_size(f_open);
        let vignetting = parse_vignetting(t)?;
        let distortion = parse_distortion(t, w, h)?;
        Ok(Self {
            f_number_open: f_open,
            f_number_pinhole: pinhole,
            pixels_per_cell: ppc,
            cells_per_mm: num("cells_per_mm", 1.0)?,
            brightness: num("brightness", 300.0)?,
            sensor,
            seed: num("seed", 1.0)? as u64,
            aperture_axis: cfg.axes.aperture.axis,
            stage_axis: cfg.axes.stage.axis,
            aperture_open: cfg.axes.aperture.open,
            aperture_pinhole: cfg.axes.aperture.pinhole,
            psf_columns: 9,
            psf_rows: 7,
            kernel_size,
            vignetting,
            distortion,
            flat_stage_mm: cfg.plan.flat.as_ref().map(|f| f.stage_mm),
            lens,
        })
    }

    /// The f-number at an aperture axis position; `None` = ideal sharp reference.
    pub fn f_number_at(&self, aperture_mm: f64) -> Option<f64> {
        let span = self.aperture_pinhole - self.aperture_open;
        let a = ((aperture_mm - self.aperture_open) / span).clamp(0.0, 1.0);
        match self.f_number_pinhole {
            None if a > 0.999 => None,
            None => Some(self.f_number_open),
            Some(p) => Some((self.f_number_open.ln() * (1.0 - a) + p.ln() * a).exp()),
        }
    }

    /// The PSF grid the camera renders with at `f_number` (the simulator's truth), its outer
    /// centres on the frame's edges (module docs).
    pub fn truth_grid(&self, f_number: f64) -> crate::optics::psf_grid::PsfGrid {
        self.lens.psf_grid_to_edges(f_number, self.psf_columns, self.psf_rows, self.kernel_size)
    }

    /// Target cell coordinates `(u0, v0)` of the undistorted pixel `(0, 0)` at a stage
    /// position: the stage slides the target by `cells_per_mm` cells per mm along x.
    pub fn target_origin(&self, stage_mm: f64) -> (f64, f64) {
        (7.0 - stage_mm * self.cells_per_mm, 5.0)
    }

    /// The sharp scene (linear reflectance) the lens images at a stage position, laid out
    /// through the distortion: sensor pixel `p` shows the target at the undistorted `D⁻¹(p)`.
    pub fn scene(&self, target: &TargetSpec, width: usize, height: usize, stage_mm: f64) -> Plane {
        let (u0, v0) = self.target_origin(stage_mm);
        match self.distortion {
            Some(d) if !d.is_none() => render_noise_scene_mapped(target, width, height, self.pixels_per_cell, u0, v0, |x, y| d.undistort_px(x, y, width, height)),
            _ => render_noise_scene(target, width, height, self.pixels_per_cell, u0, v0),
        }
    }
}

/// Why a rig config cannot make a mock camera: its `[lens]` keys (see the module docs) or its
/// `[target]`.
#[derive(Debug, thiserror::Error)]
pub enum MockError {
    #[error("lens.{key}: expected {expected}, got {got}")]
    WrongType { key: String, expected: &'static str, got: String },
    #[error("lens.{key}: unknown key (known: {known})")]
    UnknownKey { key: String, known: String },
    #[error("lens.{key}: {problem}")]
    BadValue { key: &'static str, problem: String },
    #[error("lens: need 0 < f_number_open < f_number_pinhole, got {open} and {pinhole}")]
    FNumbers { open: f64, pinhole: f64 },
    #[error("a mock camera needs [target] path = \"…toml\"")]
    NoTarget,
    #[error("target {}: {source}", path.display())]
    Target {
        path: PathBuf,
        #[source]
        source: crate::target::TargetError,
    },
}

/// The mock camera. See the module docs.
pub struct MockCamera {
    optics: MockOptics,
    target: TargetSpec,
    position: PositionSource,
    pub faults: Arc<CameraFaults>,
    exposure_us: u32,
    gain: f64,
    discard_after_change: usize,
    owed_discards: usize,
    captures: usize,
    cache: HashMap<(u64, i64), Vec<Plane>>,
    rng: Rng,
    format: FrameFormat,
    timeout: Duration,
}

impl MockCamera {
    /// # Errors
    /// Bad `[lens]` keys, a missing `[target]`, an unreadable target file.
    pub fn new(cfg: &RigConfig, position: PositionSource) -> Result<Self, MockError> {
        let optics = MockOptics::from_config(cfg)?;
        let tpath = cfg.target.as_ref().ok_or(MockError::NoTarget)?;
        let target = TargetSpec::load(&tpath.path).map_err(|source| MockError::Target { path: tpath.path.clone(), source })?;
        let faults = Arc::new(CameraFaults::default());
        if let Some(v) = cfg.lens.as_ref().and_then(|t| t.get("timeout_after_captures")).and_then(toml::Value::as_integer) {
            faults.timeout_after_captures.store(v.max(0) as usize, Ordering::SeqCst);
        }
        // Test hook (the config must stay identical for --resume): same as the key above.
        if let Some(v) = std::env::var("LENSRIG_MOCK_TIMEOUT_AFTER_CAPTURES").ok().and_then(|v| v.parse().ok()) {
            faults.timeout_after_captures.store(v, Ordering::SeqCst);
        }
        // Test hook: a panic mid-session (tests/rig_panic.rs).
        if let Some(v) = std::env::var("LENSRIG_MOCK_PANIC_AFTER_CAPTURES").ok().and_then(|v| v.parse().ok()) {
            faults.panic_after_captures.store(v, Ordering::SeqCst);
        }
        // the configured FourCC is recorded on every frame (the config's promise); the planes are
        // rendered linear whatever it names, and the frames say so (`transfer`)
        let format = FrameFormat { width: cfg.camera.width, height: cfg.camera.height, fourcc: FourCc(cfg.camera.fourcc()), transfer: Transfer::Linear };
        Ok(Self {
            rng: Rng::new(optics.seed.wrapping_mul(7919) + 17),
            optics,
            target,
            position,
            faults,
            exposure_us: cfg.camera.exposure_us,
            gain: cfg.camera.gain,
            discard_after_change: cfg.camera.discard_after_change as usize,
            owed_discards: 0,
            captures: 0,
            cache: HashMap::new(),
            format,
            timeout: Duration::from_millis(cfg.camera.frame_timeout_ms),
        })
    }

    pub fn optics(&self) -> &MockOptics {
        &self.optics
    }

    fn device(&self) -> PathBuf {
        PathBuf::from("mock")
    }

    /// The clean linear image at exposure 1 (white = 1) for the current position.
    fn clean(&mut self) -> Vec<Plane> {
        let pos = *self.position.lock().unwrap_or_else(|e| e.into_inner());
        let n = self.optics.f_number_at(pos.get(self.optics.aperture_axis));
        let stage = pos.get(self.optics.stage_axis);
        let key = (n.map_or(0, f64::to_bits), (stage * 1000.0).round() as i64);
        if let Some(c) = self.cache.get(&key) {
            return c.clone();
        }
        let (w, h) = (self.format.width as usize, self.format.height as usize);
        let bands = self.optics.lens.bands.len();
        let diffuser = self.optics.flat_stage_mm.is_some_and(|f| (f - stage).abs() < 1e-3);
        let mut clean = if diffuser {
            vec![Plane::filled(w, h, 1.0); bands]
        } else {
            let scene = self.optics.scene(&self.target, w, h, stage);
            let scene = vec![scene; bands];
            let mut shot = match n {
                Some(n) => Shot { blur: crate::optics::capture::Blur::Grid(self.optics.truth_grid(n)), ..Shot::lens(n, 1.0, self.optics.psf_columns, self.optics.psf_rows, self.optics.kernel_size) },
                None => Shot::ideal(1.0),
            };
            shot.clip = false;
            let sensor = Sensor { noise: false, ..self.optics.sensor.clone() };
            render(&scene, &self.optics.lens, &shot, &sensor, &mut Rng::new(1)).clean
        };
        if let Some(v) = &self.optics.vignetting {
            clean.iter_mut().for_each(|p| v.apply(p));
        }
        self.cache.insert(key, clean.clone());
        clean
    }

    fn white_level(&self) -> f64 {
        let pos = *self.position.lock().unwrap_or_else(|e| e.into_inner());
        // an ideal pinhole passes as much light as the pinhole f-number would
        let n = self.optics.f_number_at(pos.get(self.optics.aperture_axis)).unwrap_or(22.0);
        self.optics.brightness * self.exposure_us as f64 * 1e-6 * 10f64.powf(self.gain / 20.0) / (n * n)
    }

    fn one_frame(&mut self, clean: &[Plane], white: f64) -> Vec<Plane> {
        let g = 10f64.powf(self.gain / 20.0);
        let fw = self.optics.sensor.full_well_e;
        let read = self.optics.sensor.read_noise_e;
        let full = 65535.0f64;
        clean
            .iter()
            .map(|p| {
                let mut out = p.clone();
                for v in out.data.iter_mut() {
                    let x = (*v as f64 * white).max(0.0);
                    let var = g * x / fw + (read * g / fw).powi(2);
                    let y = (x + var.sqrt() * self.rng.normal()).clamp(0.0, 1.0);
                    *v = ((y * full).round() / full) as f32;
                }
                out
            })
            .collect()
    }
}

impl Camera for MockCamera {
    fn format(&self) -> FrameFormat {
        self.format
    }

    fn set_exposure(&mut self, us: u32) -> Result<u32, CameraError> {
        if us == 0 {
            return Err(CameraError::InvalidArgument { device: self.device(), what: "exposure must be ≥ 1 µs".into() });
        }
        if us != self.exposure_us {
            self.owed_discards = self.discard_after_change;
        }
        self.exposure_us = us;
        Ok(us)
    }

    fn set_gain(&mut self, gain: f64) -> Result<f64, CameraError> {
        if gain != self.gain {
            self.owed_discards = self.discard_after_change;
        }
        self.gain = gain.max(0.0);
        Ok(self.gain)
    }

    fn capture(&mut self, frames: usize) -> Result<Frame, CameraError> {
        let after = self.timeout;
        let limit = self.faults.timeout_after_captures.load(Ordering::SeqCst);
        if self.faults.timeout.load(Ordering::SeqCst) || (limit > 0 && self.captures >= limit) {
            return Err(CameraError::Timeout { device: self.device(), after });
        }
        let panic_after = self.faults.panic_after_captures.load(Ordering::SeqCst);
        if panic_after > 0 && self.captures >= panic_after {
            panic!("mock camera: injected panic after {} captures (test fault)", self.captures);
        }
        let stall = Duration::from_millis(self.faults.stall_once_ms.swap(0, Ordering::SeqCst));
        if !stall.is_zero() {
            std::thread::sleep(stall.min(after));
            if stall > after {
                return Err(CameraError::Timeout { device: self.device(), after });
            }
        }
        if frames == 0 {
            return Err(CameraError::InvalidArgument { device: self.device(), what: "capture needs at least one frame".into() });
        }
        let time = SystemTime::now();
        let clean = self.clean();
        let dim = self.faults.dim_captures.fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1)).is_ok();
        let white = self.white_level() * if dim { 0.7 } else { 1.0 };
        let mut discarded = std::mem::take(&mut self.owed_discards);
        let mut sum: Vec<Vec<f64>> = clean.iter().map(|p| vec![0.0; p.data.len()]).collect();
        let mut repeats = super::Repeats::default();
        let mut got = 0;
        while got < frames {
            let planes = self.one_frame(&clean, white);
            // a frame the driver dropped never arrives: count it and wait for the next one
            if self.faults.drop_frames.load(Ordering::SeqCst) > 0 {
                self.faults.drop_frames.fetch_sub(1, Ordering::SeqCst);
                discarded += 1;
                continue;
            }
            for (s, p) in sum.iter_mut().zip(&planes) {
                for (a, &v) in s.iter_mut().zip(&p.data) {
                    *a += v as f64;
                }
            }
            repeats.add(&planes);
            got += 1;
        }
        let planes: Vec<Plane> = clean
            .iter()
            .zip(&sum)
            .map(|(p, s)| Plane { width: p.width, height: p.height, data: s.iter().map(|&v| (v / frames as f64) as f32).collect() })
            .collect();
        let mut image = Image::new(planes);
        image.channels = self.optics.lens.channel_names();
        image.format = SampleFormat::U16;
        image.transfer = Transfer::Linear;
        self.captures += 1;
        Ok(Frame {
            image,
            meta: FrameMeta::new(time, self.exposure_us, self.gain, (frames, discarded), Transfer::Linear, self.format.fourcc, Some(self.captures as u32)),
            temporal_variance: repeats.variance(),
        })
    }

    fn invalidate(&mut self) {
        self.owed_discards = self.discard_after_change;
    }

    fn describe(&self) -> String {
        format!(
            "mock camera (simulated lens f/{} open, pinhole {}), {}x{} {} linear",
            self.optics.f_number_open,
            self.optics.f_number_pinhole.map_or("ideal".to_string(), |n| format!("f/{n}")),
            self.format.width,
            self.format.height,
            self.format.fourcc
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::config;

    fn cam() -> (MockCamera, PositionSource) {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("rig-configs");
        let mut cfg = config::load(&dir.join("mock.toml")).unwrap();
        cfg.camera.width = 96;
        cfg.camera.height = 72;
        let pos = Arc::new(Mutex::new(Position::ZERO));
        (MockCamera::new(&cfg, pos.clone()).unwrap(), pos)
    }

    fn mean(f: &Frame) -> f64 {
        f.image.planes[0].data.iter().map(|&v| v as f64).sum::<f64>() / f.image.planes[0].data.len() as f64
    }

    /// The truth grid samples the lens on the frame's edges: its corner kernel is the lens's
    /// PSF at the corner pixel, not one half a tile inwards that the blend would hold there.
    #[test]
    fn the_truth_grid_follows_the_lens_to_the_corners() {
        let (c, _) = cam();
        let o = c.optics();
        let g = o.truth_grid(o.f_number_open);
        assert_eq!((g.columns, g.rows), (9, 7));
        assert_eq!(g.centers, crate::optics::psf_grid::PsfGrid::edge_centers(96, 72, 9, 7));
        let (last, k) = (g.tile_count() - 1, o.kernel_size);
        for ch in 0..g.channels.len() {
            let corner = o.lens.psf(o.f_number_open, ch, 95.0, 71.0, k);
            assert!(g.kernel_at(ch, 95.0, 71.0).data.iter().zip(&corner.data).all(|(a, b)| (a - b).abs() < 1e-6));
            assert_eq!(g.kernels[ch][last].data, corner.data);
        }
        // the old tile-centred sampling put the last centre 5 px inwards (96 / 9 / 2), where the
        // red PSF differs from the corner's
        let inward = o.lens.psf(o.f_number_open, 0, 90.17, 66.36, k);
        let diff: f32 = inward.data.iter().zip(&g.kernels[0][last].data).map(|(a, b)| (a - b).abs()).sum();
        assert!(diff > 1e-3, "{diff}");
    }

    #[test]
    fn aperture_position_maps_to_f_number_and_light() {
        let (mut c, pos) = cam();
        c.optics.f_number_pinhole = Some(22.0);
        let o = c.optics().clone();
        assert!((o.f_number_at(o.aperture_open).unwrap() - o.f_number_open).abs() < 1e-9);
        assert!((o.f_number_at(o.aperture_pinhole).unwrap() - 22.0).abs() < 1e-9);
        pos.lock().unwrap().set(o.aperture_axis, o.aperture_open);
        let open = c.capture(1).unwrap();
        pos.lock().unwrap().set(o.aperture_axis, o.aperture_pinhole);
        let pin = c.capture(1).unwrap();
        let ratio = mean(&open) / mean(&pin);
        let want = (22.0f64 / o.f_number_open).powi(2);
        assert!((ratio / want - 1.0).abs() < 0.05, "{ratio} vs {want}");
    }

    #[test]
    fn averaging_lowers_noise_and_overexposure_clips() {
        let (mut c, pos) = cam();
        let o = c.optics().clone();
        pos.lock().unwrap().set(o.aperture_axis, o.aperture_open);
        let d = |a: &Frame, b: &Frame| {
            let n = a.image.planes[0].data.len() as f64;
            (a.image.planes[0].data.iter().zip(&b.image.planes[0].data).map(|(x, y)| ((x - y) as f64).powi(2)).sum::<f64>() / n).sqrt()
        };
        let (a1, b1) = (c.capture(1).unwrap(), c.capture(1).unwrap());
        let (a16, b16) = (c.capture(16).unwrap(), c.capture(16).unwrap());
        let r = d(&a1, &b1) / d(&a16, &b16);
        assert!((r - 4.0).abs() < 0.6, "noise ratio {r}");
        c.set_exposure(1_000_000).unwrap();
        let f = c.capture(1).unwrap();
        assert!(f.image.planes[0].data.iter().filter(|&&v| v >= 1.0).count() > 100);
        assert_eq!(f.meta.frames_discarded, 2);
        // the configured pixel format (rig-configs/mock.toml: BYR2) is what the frames record
        assert_eq!(f.meta.fourcc, FourCc(*b"BYR2"));
        assert_eq!(f.meta.transfer, Transfer::Linear);
    }

    /// The temporal variance over averaged frames is the sensor's Poisson–Gaussian law
    /// `Var = g·L/FW + (g·σ_read/FW)²` (single frame, full-scale axis), and a single frame has
    /// none.
    #[test]
    fn repeated_frames_measure_the_sensor_noise_law() {
        let (mut c, pos) = cam();
        let o = c.optics().clone();
        pos.lock().unwrap().set(o.aperture_axis, o.aperture_open);
        assert!(c.capture(1).unwrap().temporal_variance.is_none());
        let f = c.capture(8).unwrap();
        let var = f.temporal_variance.as_ref().expect("8 frames give a temporal variance");
        let curve = super::super::temporal_noise_curve(&f.image.planes[0], &var[0], 8);
        assert_eq!(curve.len(), 8);
        let g = 10f64.powf(c.gain / 20.0);
        let (fw, rd) = (o.sensor.full_well_e, o.sensor.read_noise_e);
        for [level, v, n] in curve {
            let want = g * level / fw + (rd * g / fw).powi(2);
            assert!(n > 100.0 && (v / want - 1.0).abs() < 0.12, "level {level:.3}: variance {v:.3e} vs law {want:.3e} ({n} px)");
        }
    }

    /// At the flat step's stage position the camera sees a uniform field through the
    /// configured `pa` vignetting: the frame's centre-to-corner ratio is `V(1)`.
    #[test]
    fn the_diffuser_renders_the_vignetting() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("rig-configs");
        let text = std::fs::read_to_string(dir.join("mock.toml")).unwrap().replace("vignetting = [-0.3, 0.05, 0.0]", "vignetting = [-0.3, 0.05]");
        assert!(text.contains("vignetting = [-0.3, 0.05]\n"));
        let mut cfg = config::parse(&text, &dir.join("mock.toml")).unwrap();
        cfg.target.as_mut().unwrap().path = dir.join("../targets/a4-noise-300dpi.toml");
        cfg.camera.width = 96;
        cfg.camera.height = 72;
        let pos = Arc::new(Mutex::new(Position::ZERO));
        let mut c = MockCamera::new(&cfg, pos.clone()).unwrap();
        let o = c.optics().clone();
        assert_eq!(o.vignetting, Some(PaVignetting { k: [-0.3, 0.05, 0.0] }));
        pos.lock().unwrap().set(o.aperture_axis, o.aperture_open);
        pos.lock().unwrap().set(o.stage_axis, cfg.plan.flat.as_ref().unwrap().stage_mm);
        c.set_exposure(20_000).unwrap();
        let f = c.capture(16).unwrap();
        let p = &f.image.planes[1];
        let block = |x0: usize, y0: usize| (y0..y0 + 4).flat_map(|y| (x0..x0 + 4).map(move |x| (x, y))).map(|(x, y)| p.get(x, y) as f64 / o.vignetting.unwrap().gain(x as f64, y as f64, 96, 72)).sum::<f64>() / 16.0;
        // divided by V, every block is the same white level
        let (centre, corner) = (block(46, 34), block(0, 0));
        assert!(centre > 0.15 && (corner / centre - 1.0).abs() < 0.01, "{centre} {corner}");
        assert!(((p.get(0, 0) / p.get(48, 36)) as f64 - 0.75).abs() < 0.03);
        let e = config::parse(&text.replace("[-0.3, 0.05]", "[-1.5]"), &dir.join("mock.toml")).map(|c| MockOptics::from_config(&c));
        assert!(matches!(e, Ok(Err(m)) if m.to_string().contains("lens.vignetting")));
    }

    /// `[lens] distortion` lays the target out through lensfun's ptlens map: the centre is
    /// unmoved, a corner pixel shows the target where the undistorted scene has it at
    /// `D⁻¹(p)`; a folding map, a wrong type and an unknown key are config errors.
    #[test]
    fn distortion_moves_the_target_and_bad_values_are_rejected() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("rig-configs");
        // mock.toml without its own distortion line
        let base: String = std::fs::read_to_string(dir.join("mock.toml")).unwrap().lines().filter(|l| !l.starts_with("distortion =")).map(|l| format!("{l}\n")).collect();
        let with = |line: &str| {
            let text = format!("{base}\n{line}\n");
            config::parse(&text, &dir.join("mock.toml")).map(|mut c| {
                c.camera.width = 96;
                c.camera.height = 72;
                MockOptics::from_config(&c)
            })
        };
        let o = with("distortion = [0.0, -0.05]").unwrap().unwrap();
        assert_eq!(o.distortion, Some(PtLens { a: 0.0, b: -0.05, c: 0.0 }));
        let t = TargetSpec::load(&dir.join("../targets/a4-noise-300dpi.toml")).unwrap();
        let (w, h) = (96, 72);
        let bent = o.scene(&t, w, h, -20.0);
        let (u0, v0) = o.target_origin(-20.0);
        let straight = render_noise_scene(&t, w, h, o.pixels_per_cell, u0, v0);
        let d = o.distortion.unwrap();
        // centre pixels barely move; a corner pixel is displaced by more than a pixel
        assert!((bent.get(48, 36) - straight.get(48, 36)).abs() < 0.05);
        let (dx, dy) = d.displacement_px(0.0, 0.0, w, h);
        assert!(dx.hypot(dy) > 1.0, "{dx} {dy}");
        // the distorted frame agrees with the straight one sampled at D⁻¹(p) (to the supersampling)
        let agree = (4..20).flat_map(|y| (4..20).map(move |x| (x, y))).filter(|&(x, y)| {
            let (xu, yu) = d.undistort_px(x as f64, y as f64, w, h);
            let one = render_noise_scene(&t, 1, 1, o.pixels_per_cell, u0 + xu / o.pixels_per_cell, v0 + yu / o.pixels_per_cell);
            (one.get(0, 0) - bent.get(x, y)).abs() < 0.2
        });
        assert!(agree.count() > 16 * 16 * 9 / 10);
        assert!(matches!(with("distortion = [0.0, -0.4]"), Ok(Err(m)) if m.to_string().contains("lens.distortion") && m.to_string().contains("monotonic")));
        assert!(matches!(with("distortion = \"barrel\""), Ok(Err(m)) if m.to_string().contains("lens.distortion")));
        assert!(matches!(with("distortoin = [0.0, -0.02]"), Ok(Err(m)) if m.to_string().contains("unknown key")));
    }

    #[test]
    fn faults_time_out_and_dropped_frames_are_replaced() {
        let (mut c, _) = cam();
        c.faults.drop_frames.store(2, Ordering::SeqCst);
        let f = c.capture(3).unwrap();
        assert_eq!((f.meta.frames_averaged, f.meta.frames_discarded), (3, 2));
        // a stall longer than the configured timeout fails once, after the timeout
        c.timeout = Duration::from_millis(100);
        c.faults.stall_once_ms.store(400, Ordering::SeqCst);
        let t0 = std::time::Instant::now();
        let e = c.capture(1).unwrap_err();
        assert!(matches!(e, CameraError::Timeout { after, .. } if after == Duration::from_millis(100)), "{e}");
        assert!((100..350).contains(&t0.elapsed().as_millis()), "{:?}", t0.elapsed());
        c.capture(1).unwrap();
        // dimmed captures see 70 % of the light, then it is back
        let level = |f: &Frame| f.image.planes[0].data.iter().map(|&v| v as f64).sum::<f64>();
        let bright = level(&c.capture(1).unwrap());
        c.faults.dim_captures.store(1, Ordering::SeqCst);
        let dim = level(&c.capture(1).unwrap());
        assert!((dim / bright - 0.7).abs() < 0.02, "{}", dim / bright);
        assert!((level(&c.capture(1).unwrap()) / bright - 1.0).abs() < 0.02);
        c.faults.timeout.store(true, Ordering::SeqCst);
        let e = c.capture(1).unwrap_err();
        assert!(matches!(e, CameraError::Timeout { .. }), "{e}");
    }
}
