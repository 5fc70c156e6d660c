//! Property tests for every parser and loader: PNG and TIFF at every supported bit depth
//! (exact round trips, then random corruption), the profile (`profile.toml` plus mosaic), rig
//! configs, session sidecars and grbl lines. Corrupted inputs go through the fuzz target
//! bodies (`fuzz/targets.rs`): no panic, and every failure a one-line error.

#[path = "../fuzz/targets.rs"]
mod targets;

use lensrig::image::io::decode_image;
use lensrig::image::SampleFormat;
use proptest::prelude::*;
use std::path::Path;

/// The supported layouts: (name, channels, bits, float).
const LAYOUTS: [(&str, usize, u32, bool); 11] = [
    ("png", 1, 8, false),
    ("png", 3, 8, false),
    ("png", 1, 16, false),
    ("png", 3, 16, false),
    ("png-alpha", 2, 8, false),
    ("tiff", 1, 8, false),
    ("tiff", 3, 8, false),
    ("tiff", 1, 16, false),
    ("tiff", 3, 16, false),
    ("tiff", 1, 32, true),
    ("tiff", 3, 32, true),
];

/// Encodes `codes` (interleaved, already in range for the depth) and returns the file bytes
/// and the values the loader must produce per channel (alpha dropped).
fn encode(layout: usize, w: u32, h: u32, codes: &[u32], floats: &[f32]) -> (Vec<u8>, Vec<Vec<f32>>) {
    use image::ExtendedColorType as E;
    use tiff::encoder::colortype as T;
    let (kind, nch, bits, float) = LAYOUTS[layout];
    let n = (w * h) as usize;
    let color = if kind == "png-alpha" { 1 } else { nch };
    let full = if bits == 8 { 255.0 } else { 65535.0 };
    let mut expect = vec![Vec::with_capacity(n); color];
    for i in 0..n {
        for (c, e) in expect.iter_mut().enumerate() {
            e.push(if float { floats[i * nch + c] } else { codes[i * nch + c] as f32 / full });
        }
    }
    let bytes = if kind.starts_with("png") {
        let raw: Vec<u8> = if bits == 8 {
            codes.iter().enumerate().map(|(i, &v)| if kind == "png-alpha" && i % 2 == 1 { 255 } else { v as u8 }).collect()
        } else {
            codes.iter().flat_map(|&v| (v as u16).to_ne_bytes()).collect()
        };
        let ct = match (nch, bits) {
            (1, 8) => E::L8,
            (2, 8) => E::La8,
            (3, 8) => E::Rgb8,
            (1, 16) => E::L16,
            _ => E::Rgb16,
        };
        let mut out = Vec::new();
        image::ImageEncoder::write_image(image::codecs::png::PngEncoder::new(&mut out), &raw, w, h, ct).unwrap();
        out
    } else {
        let mut out = std::io::Cursor::new(Vec::new());
        let mut enc = tiff::encoder::TiffEncoder::new(&mut out).unwrap();
        let u8s: Vec<u8> = codes.iter().map(|&v| v as u8).collect();
        let u16s: Vec<u16> = codes.iter().map(|&v| v as u16).collect();
        match (nch, bits) {
            (1, 8) => enc.write_image::<T::Gray8>(w, h, &u8s),
            (3, 8) => enc.write_image::<T::RGB8>(w, h, &u8s),
            (1, 16) => enc.write_image::<T::Gray16>(w, h, &u16s),
            (3, 16) => enc.write_image::<T::RGB16>(w, h, &u16s),
            (1, _) => enc.write_image::<T::Gray32Float>(w, h, floats),
            _ => enc.write_image::<T::RGB32Float>(w, h, floats),
        }
        .unwrap();
        out.into_inner()
    };
    (bytes, expect)
}

fn image_case() -> impl Strategy<Value = (usize, u32, u32, Vec<u32>, Vec<f32>)> {
    (0..LAYOUTS.len(), 1u32..10, 1u32..8).prop_flat_map(|(l, w, h)| {
        let n = (w * h) as usize * LAYOUTS[l].1;
        let max = if LAYOUTS[l].2 == 8 { 255u32 } else { 65535 };
        (Just(l), Just(w), Just(h), proptest::collection::vec(0..=max, n), proptest::collection::vec(-2.0f32..4.0, n))
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]

    #[test]
    fn images_round_trip_exactly_at_every_depth((l, w, h, codes, floats) in image_case()) {
        let (bytes, expect) = encode(l, w, h, &codes, &floats);
        let img = decode_image(Path::new("p.img"), &bytes).unwrap();
        let (_, _, bits, float) = LAYOUTS[l];
        prop_assert_eq!(img.format, match (bits, float) { (8, _) => SampleFormat::U8, (16, _) => SampleFormat::U16, _ => SampleFormat::F32 });
        prop_assert_eq!((img.width(), img.height()), (w as usize, h as usize));
        let got: Vec<Vec<f32>> = img.planes.iter().map(|p| p.data.clone()).collect();
        prop_assert_eq!(got, expect);
    }

    #[test]
    fn corrupted_images_fail_in_one_line_or_load(
        (l, w, h, codes, floats) in image_case(),
        edits in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..12),
        cut in proptest::option::of(any::<prop::sample::Index>()),
    ) {
        let (mut bytes, _) = encode(l, w, h, &codes, &floats);
        for (i, b) in &edits {
            let k = i.index(bytes.len());
            bytes[k] = *b;
        }
        if let Some(c) = cut {
            bytes.truncate(c.index(bytes.len()));
        }
        targets::image(&bytes);
    }

    #[test]
    fn corrupted_profiles_fail_in_one_line_or_are_valid(
        edits in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
        text_edits in proptest::collection::vec((any::<prop::sample::Index>(), "[0-9.\\-=\\[\\]a-z\"\n ]{0,4}"), 0..4),
    ) {
        let seed = profile_seed();
        let split = seed.iter().position(|&b| b == 0).unwrap();
        let mut text = String::from_utf8(seed[..split].to_vec()).unwrap();
        for (i, s) in &text_edits {
            let mut k = i.index(text.len() + 1);
            while !text.is_char_boundary(k) { k -= 1; }
            text.insert_str(k, s);
        }
        let mut mosaic = seed[split + 1..].to_vec();
        for (i, b) in &edits {
            let k = i.index(mosaic.len());
            mosaic[k] = *b;
        }
        let mut input = text.into_bytes();
        input.push(0);
        input.extend(mosaic);
        targets::profile(&input);
    }

    #[test]
    fn mutated_rig_configs_fail_in_one_line(
        cuts in proptest::collection::vec((any::<prop::sample::Index>(), 0usize..6, "[0-9a-z_=\\[\\]\". \n-]{0,6}"), 1..6),
    ) {
        let mut text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("rig-configs/mock.toml")).unwrap();
        for (i, del, ins) in &cuts {
            let mut k = i.index(text.len() + 1);
            while !text.is_char_boundary(k) { k -= 1; }
            let mut end = (k + del).min(text.len());
            while !text.is_char_boundary(end) { end += 1; }
            text.replace_range(k..end, ins);
        }
        targets::rig_config(text.as_bytes());
    }

    #[test]
    fn session_sidecars_round_trip_and_mutations_fail_in_one_line(
        exposure in any::<u32>(), gain in 0.0f64..64.0, stage in -500.0f64..500.0, frames in 1usize..64,
        seq in proptest::option::of(any::<u32>()),
        noise in proptest::collection::vec(proptest::collection::vec(prop::array::uniform3(0.0f64..1.0), 0..4), 0..3),
        cut in any::<prop::sample::Index>(), ins in "[0-9a-z_=\\[\\]\". \n-]{0,6}",
    ) {
        let f = lensrig::rig::session::FrameRecord {
            role: "pinhole".into(), time: "t".into(), exposure_us: exposure, gain, aperture_mm: -1.0, stage_mm: stage,
            frames_averaged: frames, frames_discarded: 0, transfer: "linear".into(), fourcc: "Y16 ".into(), sequence: seq,
            temporal_noise: Some(noise),
        };
        let text = toml::to_string_pretty(&f).unwrap();
        let back: lensrig::rig::session::FrameRecord = toml::from_str(&text).unwrap();
        prop_assert_eq!(&back, &f);
        let mut bad = text.clone();
        let mut k = cut.index(bad.len() + 1);
        while !bad.is_char_boundary(k) { k -= 1; }
        bad.insert_str(k, &ins);
        targets::session(bad.as_bytes());
    }

    #[test]
    fn grbl_lines_never_panic(line in "[<>|:,.A-Za-z0-9\\[\\]$=\\- ]{0,80}") {
        targets::grbl_line(line.as_bytes());
    }
}

/// The seed profile of the fuzz corpus (see examples/fuzz_stable.rs), built the same way.
fn profile_seed() -> Vec<u8> {
    use lensrig::optics::psf_grid::PsfGrid;
    use lensrig::profile::{Profile, PsfTable, SourceInfo};
    let ker = || lensrig::image::Plane::from_vec(3, 3, vec![0.0, 0.1, 0.0, 0.1, 0.6, 0.1, 0.0, 0.1, 0.0]).unwrap();
    let grid = PsfGrid { kernel_size: 3, columns: 2, rows: 1, centers: PsfGrid::regular_centers(40, 20, 2, 1), channels: vec!["Y".into()], kernels: vec![vec![ker(), ker()]] };
    let source = SourceInfo {
        width: 40, height: 20, channels: vec!["Y".into()], sample_format: SampleFormat::U16,
        transfer: lensrig::image::Transfer::Linear, open: None, pinhole: None, black_level: vec![],
    };
    let psf = PsfTable { kernel_size: 3, columns: 2, rows: 1, centers: grid.centers.clone(), tile_size: Some([20, 20]), files: Default::default() };
    let p = Profile { meta: Profile::new_meta(source, vec![2.0], psf), grid };
    let d = tempfile::tempdir().unwrap();
    p.save(d.path()).unwrap();
    let mut bytes = std::fs::read(d.path().join("profile.toml")).unwrap();
    bytes.push(0);
    bytes.extend(std::fs::read(d.path().join("psf-Y.tiff")).unwrap());
    // the seed itself loads
    targets::profile(&bytes);
    assert!(Profile::load(d.path()).is_ok());
    bytes
}
