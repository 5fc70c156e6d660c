//! `calibrate` on the RGB mock rig writes an `index.html` whose every image exists and decodes,
//! and which renders in headless Chromium with no broken image (checked from inside the page
//! after load, via `--dump-dom`); the screenshot is kept in the test output directory
//! (`CARGO_TARGET_TMPDIR/report-html/`). Without Chromium that part is skipped with a message
//! (run with `--nocapture` to see it). Also `lensrig report` on one of the profiles.

use std::path::{Path, PathBuf};
use std::process::Command;

fn lensrig(args: &[&str]) -> String {
    let o = Command::new(env!("CARGO_BIN_EXE_lensrig")).args(args).output().expect("run lensrig");
    assert!(o.status.success(), "{args:?}: {}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).to_string()
}

/// Every `src="…"` of the page.
fn sources(html: &str) -> Vec<String> {
    html.split("src=\"").skip(1).filter_map(|s| s.split('"').next()).map(str::to_string).collect()
}

fn check_assets(dir: &Path, html: &str) -> usize {
    let srcs = sources(html);
    for s in &srcs {
        let p = dir.join(s);
        let bytes = std::fs::read(&p).unwrap_or_else(|e| panic!("{s}: {e}"));
        if s.ends_with(".png") {
            image::load_from_memory(&bytes).unwrap_or_else(|e| panic!("{s} does not decode: {e}"));
        } else if s.ends_with(".svg") {
            let t = String::from_utf8(bytes).expect("utf-8 svg");
            assert!(t.starts_with("<svg xmlns=\"http://www.w3.org/2000/svg\"") && t.ends_with("</svg>"), "{s}");
            assert!(!t.contains("NaN") && !t.contains("inf"), "{s} has a non-finite number");
        } else {
            panic!("unexpected asset {s}");
        }
    }
    srcs.len()
}

fn chromium() -> Option<PathBuf> {
    ["/usr/bin/chromium", "/usr/bin/chromium-browser", "/usr/bin/google-chrome"].iter().map(PathBuf::from).find(|p| p.is_file())
}

fn chromium_args(profile: &Path) -> Vec<String> {
    ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync", "--hide-scrollbars"]
        .iter()
        .map(|s| s.to_string())
        .chain([format!("--user-data-dir={}", profile.display())])
        .collect()
}

#[test]
fn calibrate_report_renders_in_chromium() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let d = tempfile::tempdir().expect("tempdir");
    let target = root.join("targets/a4-noise-300dpi.toml");
    let text = std::fs::read_to_string(root.join("rig-configs/mock.toml"))
        .expect("mock.toml")
        .replace("\"../targets/a4-noise-300dpi.toml\"", &format!("{:?}", target.display().to_string()))
        .replace("width = 384", "width = 192")
        .replace("height = 288", "height = 144")
        .replace("positions = [-20.0, -40.0, -60.0]", "positions = [-20.0]")
        .replace("frames_to_average = 16", "frames_to_average = 4");
    assert!(text.contains("bands = \"rgb\""), "mock.toml is the RGB rig");
    let cfg = d.path().join("rig.toml");
    std::fs::write(&cfg, text).expect("config");
    let out = d.path().join("cal");
    let stdout = lensrig(&["calibrate", "--rig", cfg.to_str().unwrap_or_default(), "--out", out.to_str().unwrap_or_default(), "--quiet"]);
    println!("{stdout}");
    let html = std::fs::read_to_string(out.join("index.html")).expect("index.html");
    for must in ["psf-rgb.png", "psf-R.png", "psf-G.png", "psf-B.png", "mtf50-G-tan.svg", "mtf-curves-B.svg", "lateral-colour.svg", "MTF50 against the simulator's truth", "lp/mm"] {
        assert!(html.contains(must), "index.html lacks {must}");
    }
    assert!(!html.contains("0.9648859300744004") && !html.contains("NaN"));
    let n = check_assets(&out, &html);
    assert!(n >= 12, "only {n} images");
    let summary = std::fs::read_to_string(out.join("summary.json")).expect("summary");
    assert!(summary.contains("mtf50_median_relative_difference_vs_truth"), "{summary}");

    // `lensrig report` on the profile alone
    let key = std::fs::read_dir(out.join("profiles")).expect("profiles").filter_map(|e| e.ok()).map(|e| e.path()).find(|p| p.join("profile.toml").is_file()).expect("a profile");
    let rep = d.path().join("rep");
    let s = lensrig(&["report", "--profile", key.to_str().unwrap_or_default(), "--out", rep.to_str().unwrap_or_default(), "--rig", cfg.to_str().unwrap_or_default()]);
    assert!(s.contains("lp/mm"), "{s}");
    let rhtml = std::fs::read_to_string(rep.join("index.html")).expect("report index");
    check_assets(&rep, &rhtml);
    let csv = std::fs::read_to_string(rep.join("mtf50.csv")).expect("csv");
    assert!(csv.lines().count() > 3 && !csv.contains("NaN"));

    let Some(chrome) = chromium() else {
        eprintln!("SKIPPED the Chromium check: no chromium found (apt-get install chromium)");
        println!("SKIPPED the Chromium check: no chromium found (apt-get install chromium)");
        return;
    };
    // a copy of the page that records, after load, which images failed to decode
    let probe = html.replace(
        "</style>",
        "</style><script>window.addEventListener('load',()=>{const b=[...document.images].filter(i=>!i.complete||i.naturalWidth===0).map(i=>i.getAttribute('src'));document.documentElement.setAttribute('data-images',document.images.length);document.documentElement.setAttribute('data-broken',b.join(' ')||'none');});</script>",
    );
    let probe_path = out.join("check.html");
    std::fs::write(&probe_path, probe).expect("check.html");
    let udir = tempfile::tempdir().expect("user data dir");
    let o = Command::new(&chrome)
        .args(chromium_args(udir.path()))
        .args(["--virtual-time-budget=10000", "--dump-dom"])
        .arg(format!("file://{}", probe_path.display()))
        .output()
        .expect("chromium");
    let dom = String::from_utf8_lossy(&o.stdout);
    assert!(dom.contains("data-broken=\"none\""), "broken images in Chromium: {}", dom.split("data-broken=\"").nth(1).and_then(|s| s.split('"').next()).unwrap_or("(no check ran)"));
    assert!(dom.contains(&format!("data-images=\"{n}\"")), "Chromium saw a different number of images than {n}");
    let shots = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("report-html");
    std::fs::create_dir_all(&shots).expect("shots dir");
    let shot = shots.join("index.png");
    let udir2 = tempfile::tempdir().expect("user data dir");
    let o = Command::new(&chrome)
        .args(chromium_args(udir2.path()))
        .args(["--window-size=1280,2000", &format!("--screenshot={}", shot.display())])
        .arg(format!("file://{}", out.join("index.html").display()))
        .output()
        .expect("chromium screenshot");
    assert!(shot.is_file(), "no screenshot: {}", String::from_utf8_lossy(&o.stderr));
    let img = image::open(&shot).expect("screenshot decodes");
    assert_eq!((img.width(), img.height()), (1280, 2000));
    println!("screenshot: {}", shot.display());
}
