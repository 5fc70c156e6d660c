//! The stable-toolchain fuzz driver: feeds mutated inputs to the loaders of `fuzz/targets.rs`
//! for a fixed time budget per target, without libFuzzer's coverage feedback.
//!
//! ```text
//! cargo run --release --example fuzz_stable -- [--seconds S] [--seed N] [TARGET...]
//! ```
//! Seeds are written to `fuzz/corpus/<target>/` (when missing) and read from there, so the
//! `cargo fuzz` targets start from the same corpus. Each execution takes one corpus entry and
//! applies 1–8 random mutations (bit flips, random or extreme bytes, inserted, deleted or
//! duplicated ranges, truncation, splices with another entry). A panic is a crash: the input is
//! saved to `fuzz/artifacts/<target>/crash-<hash>` and the driver exits 1. Per target it prints
//! one table row: corpus entries and bytes, seconds, executions, slowest execution and peak
//! heap in use during one execution (a counting allocator), the guard against hangs and
//! unbounded allocation.

#[path = "../fuzz/targets.rs"]
mod targets;

use std::alloc::{GlobalAlloc, Layout, System};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

struct Counting;
static IN_USE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards to the system allocator; only counts bytes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        let p = System.alloc(l);
        if !p.is_null() {
            let now = IN_USE.fetch_add(l.size(), Ordering::Relaxed) + l.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        IN_USE.fetch_sub(l.size(), Ordering::Relaxed);
        System.dealloc(p, l)
    }
}

#[global_allocator]
static A: Counting = Counting;

/// xorshift64*: the mutation source (seeded, reproducible).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next() % n as u64) as usize
        }
    }
}

fn mutate(rng: &mut Rng, corpus: &[Vec<u8>], base: &[u8]) -> Vec<u8> {
    let mut d = base.to_vec();
    for _ in 0..1 + rng.below(8) {
        let n = d.len();
        match rng.below(8) {
            0 if n > 0 => {
                let i = rng.below(n);
                d[i] ^= 1 << rng.below(8);
            }
            1 if n > 0 => {
                let i = rng.below(n);
                d[i] = rng.next() as u8;
            }
            2 if n > 0 => {
                // an extreme value: 0, 0xff.., 0x7f.., 0x80..
                let v: [u8; 4] = [[0, 0, 0, 0], [0xff; 4], [0x7f, 0xff, 0xff, 0xff], [0x80, 0, 0, 0]][rng.below(4)];
                let i = rng.below(n);
                for (k, b) in v.iter().enumerate().take(1 + rng.below(4)) {
                    if let Some(x) = d.get_mut(i + k) {
                        *x = *b;
                    }
                }
            }
            3 if n > 0 => {
                let i = rng.below(n);
                let len = rng.below((n - i).min(64)) + 1;
                d.drain(i..(i + len).min(n));
            }
            4 => {
                let i = rng.below(n + 1);
                let bytes: Vec<u8> = (0..1 + rng.below(16)).map(|_| rng.next() as u8).collect();
                d.splice(i..i, bytes);
            }
            5 if n > 0 => d.truncate(rng.below(n)),
            6 if n > 0 => {
                let i = rng.below(n);
                let len = (rng.below(64) + 1).min(n - i);
                let chunk = d[i..i + len].to_vec();
                let j = rng.below(n + 1);
                d.splice(j..j, chunk);
            }
            _ => {
                let other = &corpus[rng.below(corpus.len())];
                if !other.is_empty() {
                    let i = rng.below(other.len());
                    let cut = rng.below(d.len() + 1);
                    d.truncate(cut);
                    d.extend_from_slice(&other[i..]);
                }
            }
        }
    }
    d
}

fn png(w: u32, h: u32, ct: image::ExtendedColorType, bytes: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    image::ImageEncoder::write_image(image::codecs::png::PngEncoder::new(&mut out), bytes, w, h, ct).expect("encode seed");
    out
}

fn tiff<C: tiff::encoder::colortype::ColorType>(w: u32, h: u32, data: &[C::Inner]) -> Vec<u8>
where
    [C::Inner]: tiff::encoder::TiffValue,
{
    let mut out = std::io::Cursor::new(Vec::new());
    tiff::encoder::TiffEncoder::new(&mut out).expect("tiff").write_image::<C>(w, h, data).expect("encode seed");
    out.into_inner()
}

/// The seed inputs of `target`.
fn seeds(target: &str) -> Vec<(String, Vec<u8>)> {
    use image::ExtendedColorType as E;
    use tiff::encoder::colortype as T;
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let ramp8 = |n: usize| (0..n).map(|i| (i * 37 % 256) as u8).collect::<Vec<u8>>();
    match target {
        "image" => {
            let (w, h) = (7u32, 5u32);
            let n = (w * h) as usize;
            let u16s = |c: usize| (0..n * c).map(|i| (i * 4099 % 65536) as u16).collect::<Vec<u16>>();
            let f32s = |c: usize| (0..n * c).map(|i| i as f32 * 0.01 - 0.05).collect::<Vec<f32>>();
            let be = |v: Vec<u16>| v.iter().flat_map(|x| x.to_be_bytes()).collect::<Vec<u8>>();
            let mut la8 = ramp8(n * 2);
            la8.iter_mut().skip(1).step_by(2).for_each(|a| *a = 255);
            vec![
                ("png-l8".into(), png(w, h, E::L8, &ramp8(n))),
                ("png-la8".into(), png(w, h, E::La8, &la8)),
                ("png-rgb8".into(), png(w, h, E::Rgb8, &ramp8(n * 3))),
                ("png-l16".into(), png(w, h, E::L16, &u16s(1).iter().flat_map(|x| x.to_ne_bytes()).collect::<Vec<u8>>())),
                ("png-rgb16".into(), png(w, h, E::Rgb16, &u16s(3).iter().flat_map(|x| x.to_ne_bytes()).collect::<Vec<u8>>())),
                ("tiff-gray8".into(), tiff::<T::Gray8>(w, h, &ramp8(n))),
                ("tiff-rgb8".into(), tiff::<T::RGB8>(w, h, &ramp8(n * 3))),
                ("tiff-gray16".into(), tiff::<T::Gray16>(w, h, &u16s(1))),
                ("tiff-rgb16".into(), tiff::<T::RGB16>(w, h, &u16s(3))),
                ("tiff-gray32f".into(), tiff::<T::Gray32Float>(w, h, &f32s(1))),
                ("tiff-rgb32f".into(), tiff::<T::RGB32Float>(w, h, &f32s(3))),
                ("tiff-gray32f-nan".into(), tiff::<T::Gray32Float>(2, 2, &[0.5, f32::NAN, f32::INFINITY, -0.1])),
                ("not-an-image".into(), be(u16s(1))),
            ]
        }
        "profile" => {
            let dir = std::env::temp_dir().join(format!("lensrig-fuzz-seed-{}", std::process::id()));
            let k = 3;
            let ker = || lensrig::image::Plane::from_vec(3, 3, vec![0.0, 0.1, 0.0, 0.1, 0.6, 0.1, 0.0, 0.1, 0.0]).expect("3x3");
            let grid = lensrig::optics::psf_grid::PsfGrid {
                kernel_size: k,
                columns: 2,
                rows: 1,
                centers: lensrig::optics::psf_grid::PsfGrid::regular_centers(40, 20, 2, 1),
                channels: vec!["Y".into()],
                kernels: vec![vec![ker(), ker()]],
            };
            let source = lensrig::profile::SourceInfo {
                width: 40,
                height: 20,
                channels: vec!["Y".into()],
                sample_format: lensrig::image::SampleFormat::U16,
                transfer: lensrig::image::Transfer::Linear,
                open: None,
                pinhole: None,
                black_level: vec![],
            };
            let psf = lensrig::profile::PsfTable { kernel_size: k, columns: 2, rows: 1, centers: grid.centers.clone(), tile_size: Some([20, 20]), files: Default::default() };
            let p = lensrig::profile::Profile { meta: lensrig::profile::Profile::new_meta(source, vec![2.0], psf), grid };
            p.save(&dir).expect("seed profile");
            let mut bytes = std::fs::read(dir.join("profile.toml")).expect("seed");
            bytes.push(0);
            bytes.extend(std::fs::read(dir.join("psf-Y.tiff")).expect("seed"));
            let _ = std::fs::remove_dir_all(&dir);
            vec![("profile-y-2x1".into(), bytes)]
        }
        "rig_config" => ["mock.toml", "example-real.toml"]
            .iter()
            .map(|f| (f.replace(".toml", ""), std::fs::read(root.join("rig-configs").join(f)).expect("rig config")))
            .collect(),
        "session" => {
            let rec = lensrig::rig::session::SessionRecord {
                software: "lensrig 0.1.0".into(),
                rig_config: "rig.toml".into(),
                rig_config_copy: "rig.toml".into(),
                camera: "mock".into(),
                status: "running".into(),
                pairs: vec![lensrig::rig::session::PairRecord {
                    index: 0,
                    key: "000-stage-X-20.000".into(),
                    stage_mm: -20.0,
                    dir: "pairs/000-stage-X-20.000".into(),
                    open: "open.png".into(),
                    pinhole: "pinhole.png".into(),
                    dark: Some("dark.png".into()),
                }],
                ..Default::default()
            };
            let frame = lensrig::rig::session::FrameRecord {
                role: "open".into(),
                time: "2026-11-23T06:00:00Z".into(),
                exposure_us: 20000,
                gain: 1.0,
                frames_averaged: 4,
                transfer: "linear".into(),
                fourcc: "Y16 ".into(),
                sequence: Some(3),
                temporal_noise: Some(vec![vec![[0.1, 1e-5, 100.0], [0.5, 3e-5, 100.0]]]),
                ..Default::default()
            };
            vec![
                ("session".into(), toml::to_string_pretty(&rec).expect("toml").into_bytes()),
                ("frame".into(), toml::to_string_pretty(&frame).expect("toml").into_bytes()),
            ]
        }
        "grbl_line" => vec![
            ("status".into(), b"<Idle|MPos:0.000,-20.000,0.000|Bf:15,128|FS:0,0|WCO:0.000,0.000,0.000>".to_vec()),
            ("run".into(), b"<Run|MPos:1.5,2.25,-3|FS:500,0|Pn:XY|Ov:100,100,100|A:S>\nok\nerror:9".to_vec()),
            ("alarm".into(), b"ALARM:1\n[MSG:Reset to continue]\nGrbl 1.1h ['$' for help]\n$130=200.000".to_vec()),
        ],
        _ => vec![],
    }
}

/// The corpus of `target`, seeded on first use.
fn corpus(dir: &Path, target: &str) -> std::io::Result<Vec<Vec<u8>>> {
    if !dir.is_dir() {
        std::fs::create_dir_all(dir)?;
        for (name, bytes) in seeds(target) {
            std::fs::write(dir.join(format!("seed-{name}")), bytes)?;
        }
    }
    let mut names: Vec<PathBuf> = std::fs::read_dir(dir)?.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_file()).collect();
    names.sort();
    names.iter().map(std::fs::read).collect()
}

fn fnv(d: &[u8]) -> u64 {
    d.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x100_0000_01b3))
}

fn main() -> std::process::ExitCode {
    let mut seconds = 20.0f64;
    let mut seed = 1u64;
    let mut names = Vec::new();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--seconds" => seconds = args.next().and_then(|v| v.parse().ok()).unwrap_or(seconds),
            "--seed" => seed = args.next().and_then(|v| v.parse().ok()).unwrap_or(seed),
            t if targets::TARGETS.contains(&t) => names.push(t.to_string()),
            other => {
                eprintln!("fuzz_stable: unknown argument {other:?} (targets: {})", targets::TARGETS.join(", "));
                return std::process::ExitCode::from(2);
            }
        }
    }
    if names.is_empty() {
        names = targets::TARGETS.iter().map(|s| s.to_string()).collect();
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz");
    std::panic::set_hook(Box::new(|_| {}));
    let mut crashed = false;
    println!("| target | corpus (files, bytes) | seconds | executions | exec/s | slowest exec (ms) | peak heap per exec (MiB) | crashes |");
    println!("|---|---|---|---|---|---|---|---|");
    for name in &names {
        let corpus = match corpus(&root.join("corpus").join(name), name) {
            Ok(c) if !c.is_empty() => c,
            Ok(_) => vec![Vec::new()],
            Err(e) => {
                eprintln!("fuzz_stable: corpus for {name}: {e}");
                return std::process::ExitCode::from(2);
            }
        };
        let bytes: usize = corpus.iter().map(Vec::len).sum();
        let mut rng = Rng(seed ^ fnv(name.as_bytes()) | 1);
        let t0 = Instant::now();
        let (mut execs, mut slowest, mut peak, mut crashes) = (0u64, Duration::ZERO, 0usize, 0);
        while t0.elapsed().as_secs_f64() < seconds {
            // every corpus entry once unmutated, then mutations
            let input = if (execs as usize) < corpus.len() {
                corpus[execs as usize].clone()
            } else {
                let base = &corpus[rng.below(corpus.len())];
                mutate(&mut rng, &corpus, base)
            };
            let base_use = IN_USE.load(Ordering::Relaxed);
            PEAK.store(base_use, Ordering::Relaxed);
            let t = Instant::now();
            let r = std::panic::catch_unwind(|| targets::run(name, &input));
            slowest = slowest.max(t.elapsed());
            peak = peak.max(PEAK.load(Ordering::Relaxed).saturating_sub(base_use));
            execs += 1;
            if r.is_err() {
                crashes += 1;
                let dir = root.join("artifacts").join(name);
                let path = dir.join(format!("crash-{:016x}", fnv(&input)));
                let saved = std::fs::create_dir_all(&dir).and_then(|_| std::fs::write(&path, &input));
                eprintln!("fuzz_stable: {name}: panic; input saved to {} ({saved:?})", path.display());
                if crashes >= 5 {
                    break;
                }
            }
        }
        let secs = t0.elapsed().as_secs_f64();
        crashed |= crashes > 0;
        println!(
            "| {name} | {}, {bytes} | {secs:.1} | {execs} | {:.0} | {:.1} | {:.1} | {crashes} |",
            corpus.len(),
            execs as f64 / secs,
            slowest.as_secs_f64() * 1e3,
            peak as f64 / (1 << 20) as f64
        );
    }
    if crashed {
        std::process::ExitCode::from(1)
    } else {
        std::process::ExitCode::SUCCESS
    }
}
