//! Atomic file writes and the never-overwrite rule.
//!
//! Every file lensrig writes goes through [`write_atomic`]: the bytes land in a temporary file
//! in the destination's directory, are flushed to disk, and only then renamed over the final
//! name. A crash, a full disk or a kill leaves either the old file or the new one, never half a
//! file. Captures are written with [`Overwrite::Never`] so a user's data cannot be replaced.
//!
//! Nothing non-finite is written: images are checked by their writers
//! ([`crate::image::io`]), profiles by [`crate::profile::Profile::save`], and serialised reports
//! with [`first_non_finite`] / [`write_json_atomic`] (serde_json would silently turn NaN into
//! `null`).

use std::fs::{self, File};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

/// What to do when the destination already exists.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Overwrite {
    /// Replace it (derived outputs: reports, predictions, profiles the user asked for).
    Replace,
    /// Refuse with [`io::ErrorKind::AlreadyExists`] (captures, sessions).
    Never,
}

/// Writes `bytes` to `path` atomically (temporary file + fsync + rename).
///
/// # Errors
/// Any I/O error (including a full disk), or `AlreadyExists` under [`Overwrite::Never`]. On
/// error the temporary file is removed and `path` is untouched.
pub fn write_atomic(path: &Path, bytes: &[u8], overwrite: Overwrite) -> io::Result<()> {
    write_atomic_with(path, overwrite, |f| f.write_all(bytes))
}

/// Like [`write_atomic`], with a writer callback for encoders that stream.
///
/// # Errors
/// As [`write_atomic`], plus whatever `fill` returns.
pub fn write_atomic_with(
    path: &Path,
    overwrite: Overwrite,
    fill: impl FnOnce(&mut File) -> io::Result<()>,
) -> io::Result<()> {
    if overwrite == Overwrite::Never && path.exists() {
        return Err(io::Error::new(io::ErrorKind::AlreadyExists, format!("{} already exists and is never overwritten", path.display())));
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path.file_name().ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "path has no file name"))?;
    let tmp = dir.join(format!(".{}.tmp-{}", name.to_string_lossy(), std::process::id()));
    let result = (|| {
        let mut f = File::create(&tmp)?;
        fill(&mut f)?;
        f.flush()?;
        f.sync_all()?;
        drop(f);
        if overwrite == Overwrite::Never {
            // hard_link fails if the destination appeared meanwhile: no race with another writer.
            fs::hard_link(&tmp, path)?;
            fs::remove_file(&tmp)?;
        } else {
            fs::rename(&tmp, path)?;
        }
        Ok(())
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

/// The path (`field.sub[3]`) of the first NaN or infinite float in `value`'s serde
/// serialisation, or `None` when every number is finite.
pub fn first_non_finite<T: serde::Serialize + ?Sized>(value: &T) -> Option<String> {
    let mut f = finite::Finder { path: Vec::new() };
    match value.serialize(&mut f) {
        Ok(()) => None,
        Err(finite::Found(p)) => Some(if p.is_empty() { "(the value)".into() } else { p }),
    }
}

/// Serialises `value` as pretty JSON and writes it atomically, refusing (before anything is
/// written) a value with a non-finite number.
///
/// # Errors
/// `InvalidData` naming the field of a non-finite number; serialisation and I/O errors as
/// [`write_atomic`].
pub fn write_json_atomic<T: serde::Serialize + ?Sized>(path: &Path, value: &T, overwrite: Overwrite) -> io::Result<()> {
    if let Some(field) = first_non_finite(value) {
        return Err(io::Error::new(io::ErrorKind::InvalidData, format!("refusing to write {}: {field} is not a finite number (a bug: please report it)", path.display())));
    }
    let text = serde_json::to_string_pretty(value).map_err(io::Error::other)?;
    write_atomic(path, text.as_bytes(), overwrite)
}

mod finite {
    //! A serde serializer that only looks for non-finite floats and remembers where.
    use serde::ser::{self, Serialize};

    pub struct Finder {
        pub path: Vec<String>,
    }

    #[derive(Debug)]
    pub struct Found(pub String);

    impl std::fmt::Display for Found {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            write!(f, "non-finite number at {}", self.0)
        }
    }
    impl std::error::Error for Found {}
    impl ser::Error for Found {
        fn custom<T: std::fmt::Display>(_: T) -> Self {
            Found(String::new())
        }
    }

    impl Finder {
        fn here(&self) -> String {
            self.path.iter().fold(String::new(), |mut a, p| {
                if !a.is_empty() && !p.starts_with('[') {
                    a.push('.');
                }
                a.push_str(p);
                a
            })
        }
        fn float(&mut self, v: f64) -> Result<(), Found> {
            if v.is_finite() {
                Ok(())
            } else {
                Err(Found(self.here()))
            }
        }
        fn at<T: Serialize + ?Sized>(&mut self, seg: String, v: &T) -> Result<(), Found> {
            self.path.push(seg);
            let r = v.serialize(&mut *self);
            self.path.pop();
            r
        }
    }

    /// Sequence/map state: the index of the next element.
    pub struct Compound<'a> {
        f: &'a mut Finder,
        i: usize,
        key: Option<String>,
    }

    macro_rules! ok_scalars {
        ($($name:ident: $t:ty),*) => { $(fn $name(self, _: $t) -> Result<(), Found> { Ok(()) })* };
    }

    impl<'a> ser::Serializer for &'a mut Finder {
        type Ok = ();
        type Error = Found;
        type SerializeSeq = Compound<'a>;
        type SerializeTuple = Compound<'a>;
        type SerializeTupleStruct = Compound<'a>;
        type SerializeTupleVariant = Compound<'a>;
        type SerializeMap = Compound<'a>;
        type SerializeStruct = Compound<'a>;
        type SerializeStructVariant = Compound<'a>;
        ok_scalars!(serialize_bool: bool, serialize_i8: i8, serialize_i16: i16, serialize_i32: i32, serialize_i64: i64,
            serialize_u8: u8, serialize_u16: u16, serialize_u32: u32, serialize_u64: u64, serialize_char: char,
            serialize_str: &str, serialize_bytes: &[u8]);
        fn serialize_f32(self, v: f32) -> Result<(), Found> {
            self.float(v as f64)
        }
        fn serialize_f64(self, v: f64) -> Result<(), Found> {
            self.float(v)
        }
        fn serialize_none(self) -> Result<(), Found> {
            Ok(())
        }
        fn serialize_some<T: Serialize + ?Sized>(self, v: &T) -> Result<(), Found> {
            v.serialize(self)
        }
        fn serialize_unit(self) -> Result<(), Found> {
            Ok(())
        }
        fn serialize_unit_struct(self, _: &'static str) -> Result<(), Found> {
            Ok(())
        }
        fn serialize_unit_variant(self, _: &'static str, _: u32, _: &'static str) -> Result<(), Found> {
            Ok(())
        }
        fn serialize_newtype_struct<T: Serialize + ?Sized>(self, _: &'static str, v: &T) -> Result<(), Found> {
            v.serialize(self)
        }
        fn serialize_newtype_variant<T: Serialize + ?Sized>(self, _: &'static str, _: u32, var: &'static str, v: &T) -> Result<(), Found> {
            self.at(var.to_string(), v)
        }
        fn serialize_seq(self, _: Option<usize>) -> Result<Compound<'a>, Found> {
            Ok(Compound { f: self, i: 0, key: None })
        }
        fn serialize_tuple(self, _: usize) -> Result<Compound<'a>, Found> {
            Ok(Compound { f: self, i: 0, key: None })
        }
        fn serialize_tuple_struct(self, _: &'static str, _: usize) -> Result<Compound<'a>, Found> {
            Ok(Compound { f: self, i: 0, key: None })
        }
        fn serialize_tuple_variant(self, _: &'static str, _: u32, _: &'static str, _: usize) -> Result<Compound<'a>, Found> {
            Ok(Compound { f: self, i: 0, key: None })
        }
        fn serialize_map(self, _: Option<usize>) -> Result<Compound<'a>, Found> {
            Ok(Compound { f: self, i: 0, key: None })
        }
        fn serialize_struct(self, _: &'static str, _: usize) -> Result<Compound<'a>, Found> {
            Ok(Compound { f: self, i: 0, key: None })
        }
        fn serialize_struct_variant(self, _: &'static str, _: u32, _: &'static str, _: usize) -> Result<Compound<'a>, Found> {
            Ok(Compound { f: self, i: 0, key: None })
        }
    }

    impl Compound<'_> {
        fn element<T: Serialize + ?Sized>(&mut self, v: &T) -> Result<(), Found> {
            let seg = format!("[{}]", self.i);
            self.i += 1;
            self.f.at(seg, v)
        }
    }

    macro_rules! seq_like {
        ($($tr:ident :: $m:ident),*) => {$(
            impl ser::$tr for Compound<'_> {
                type Ok = ();
                type Error = Found;
                fn $m<T: Serialize + ?Sized>(&mut self, v: &T) -> Result<(), Found> {
                    self.element(v)
                }
                fn end(self) -> Result<(), Found> {
                    Ok(())
                }
            }
        )*};
    }
    seq_like!(SerializeSeq::serialize_element, SerializeTuple::serialize_element, SerializeTupleStruct::serialize_field, SerializeTupleVariant::serialize_field);

    macro_rules! struct_like {
        ($($tr:ident),*) => {$(
            impl ser::$tr for Compound<'_> {
                type Ok = ();
                type Error = Found;
                fn serialize_field<T: Serialize + ?Sized>(&mut self, key: &'static str, v: &T) -> Result<(), Found> {
                    self.f.at(key.to_string(), v)
                }
                fn end(self) -> Result<(), Found> {
                    Ok(())
                }
            }
        )*};
    }
    struct_like!(SerializeStruct, SerializeStructVariant);

    /// Map keys are recorded by their JSON text (strings without quotes).
    impl ser::SerializeMap for Compound<'_> {
        type Ok = ();
        type Error = Found;
        fn serialize_key<T: Serialize + ?Sized>(&mut self, key: &T) -> Result<(), Found> {
            let k = serde_json::to_string(key).unwrap_or_default();
            self.key = Some(k.trim_matches('"').to_string());
            Ok(())
        }
        fn serialize_value<T: Serialize + ?Sized>(&mut self, v: &T) -> Result<(), Found> {
            let k = self.key.take().unwrap_or_else(|| format!("[{}]", self.i));
            self.i += 1;
            self.f.at(k, v)
        }
        fn end(self) -> Result<(), Found> {
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn non_finite_numbers_are_found_by_path_and_not_written() {
        #[derive(serde::Serialize)]
        struct Inner {
            chi2: Vec<f64>,
        }
        #[derive(serde::Serialize)]
        struct Report {
            name: String,
            ok: f32,
            rounds: Vec<Inner>,
            extra: std::collections::BTreeMap<String, Option<f64>>,
        }
        let mut r = Report { name: "x".into(), ok: 1.0, rounds: vec![Inner { chi2: vec![1.0] }, Inner { chi2: vec![2.0, f64::NAN] }], extra: Default::default() };
        assert_eq!(first_non_finite(&r).as_deref(), Some("rounds[1].chi2[1]"));
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("report.json");
        let e = write_json_atomic(&p, &r, Overwrite::Replace).unwrap_err();
        assert!(e.to_string().contains("rounds[1].chi2[1] is not a finite number"), "{e}");
        assert!(!p.exists());
        r.rounds[1].chi2[1] = 3.0;
        r.extra.insert("gain".into(), Some(f64::INFINITY));
        assert_eq!(first_non_finite(&r).as_deref(), Some("extra.gain"));
        r.extra.insert("gain".into(), None);
        assert_eq!(first_non_finite(&r), None);
        write_json_atomic(&p, &r, Overwrite::Replace).unwrap();
        assert!(std::fs::read_to_string(&p).unwrap().contains("\"chi2\""));
        assert_eq!(first_non_finite(&f32::NEG_INFINITY).as_deref(), Some("(the value)"));
    }

    #[test]
    fn never_refuses_existing_and_keeps_content() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("a.bin");
        write_atomic(&p, b"first", Overwrite::Never).unwrap();
        let e = write_atomic(&p, b"second", Overwrite::Never).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::AlreadyExists);
        assert_eq!(fs::read(&p).unwrap(), b"first");
        write_atomic(&p, b"third", Overwrite::Replace).unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"third");
        // no temporary files left behind
        assert_eq!(fs::read_dir(d.path()).unwrap().count(), 1);
    }

    #[test]
    fn failing_writer_leaves_nothing() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("b.bin");
        let e = write_atomic_with(&p, Overwrite::Replace, |f| {
            f.write_all(b"partial")?;
            Err(io::Error::other("disk full"))
        });
        assert!(e.is_err());
        assert!(!p.exists());
        assert_eq!(fs::read_dir(d.path()).unwrap().count(), 0);
    }
}
