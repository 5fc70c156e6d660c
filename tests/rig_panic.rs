//! A panic in the middle of a capture (a test-only fault in the mock camera) through the real
//! binary: the panic hook prints one line and exits 70, the session journal is consistent
//! (finished pairs recorded, the interrupted one unfinished, nothing half-written), and
//! `--resume` completes the session with the finished pairs byte-identical.

use lensrig::rig::session;
use std::path::{Path, PathBuf};
use std::process::Command;

const FILES: [&str; 6] = ["open.png", "open.toml", "pinhole.png", "pinhole.toml", "dark.png", "dark.toml"];

fn config(dir: &Path) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(root.join("rig-configs/mock.toml")).unwrap();
    let target = root.join("targets/a4-noise-300dpi.toml");
    let text = text
        .replace("\"../targets/a4-noise-300dpi.toml\"", &format!("{:?}", target.display().to_string()))
        .replace("frames_to_average = 16", "frames_to_average = 2")
        .replace("width = 384", "width = 192")
        .replace("height = 288", "height = 144");
    let p = dir.join("rig.toml");
    std::fs::write(&p, text).unwrap();
    p
}

fn capture(cfg: &Path, s: &Path, resume: bool, panic_after: Option<usize>) -> std::process::Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_lensrig"));
    c.args(["capture", "--rig", cfg.to_str().unwrap(), "--out", s.to_str().unwrap(), "--quiet"]).env_remove("RUST_BACKTRACE");
    if resume {
        c.arg("--resume");
    }
    match panic_after {
        Some(n) => c.env("LENSRIG_MOCK_PANIC_AFTER_CAPTURES", n.to_string()),
        None => c.env_remove("LENSRIG_MOCK_PANIC_AFTER_CAPTURES"),
    };
    c.output().unwrap()
}

fn snapshot(pair: &Path) -> Vec<Vec<u8>> {
    FILES.iter().map(|f| std::fs::read(pair.join(f)).unwrap_or_else(|e| panic!("{}: {e}", pair.join(f).display()))).collect()
}

fn all_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        out.push(p.clone());
        if p.is_dir() {
            all_files(&p, out);
        }
    }
}

#[test]
fn a_panic_mid_pair_leaves_a_consistent_journal_and_resume_completes() {
    let dir = std::env::temp_dir().join(format!("lensrig-panic-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let cfg = config(&dir);
    let s = dir.join("session");
    // 4 captures per pair: the 6th capture is inside the second pair
    let o = capture(&cfg, &s, false, Some(5));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(70), "{err}");
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(err.contains("internal error (a bug) while running `lensrig capture") && err.contains("injected panic after 5 captures"), "{err}");
    // the journal: the first pair finished and recorded, the second unfinished
    let rec = session::load_session(&s).unwrap();
    assert_eq!(rec.status, "running");
    assert_eq!(rec.pairs.iter().map(|p| p.key.as_str()).collect::<Vec<_>>(), ["000-stage-X-20.000"]);
    let first = s.join("pairs/000-stage-X-20.000");
    assert!(!s.join("pairs/001-stage-X-40.000").exists());
    let mut files = Vec::new();
    all_files(&s, &mut files);
    assert!(files.iter().all(|p| !p.to_string_lossy().contains(".tmp-")), "temporary file left: {files:?}");
    let before = snapshot(&first);
    // resume without the fault: complete, the finished pair untouched
    let o = capture(&cfg, &s, true, None);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let rec = session::load_session(&s).unwrap();
    assert_eq!(rec.status, "complete");
    let keys = ["000-stage-X-20.000", "001-stage-X-40.000", "002-stage-X-60.000"];
    assert_eq!(rec.pairs.iter().map(|p| p.key.as_str()).collect::<Vec<_>>(), keys);
    assert!(before == snapshot(&first), "a finished pair changed on resume");
    for k in keys {
        let d = s.join("pairs").join(k);
        for f in FILES {
            assert!(d.join(f).is_file(), "{} lacks {f}", d.display());
        }
        lensrig::image::io::read_image(&d.join("open.png")).unwrap();
    }
    let _ = std::fs::remove_dir_all(&dir);
}
