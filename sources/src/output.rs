//! Files the tools write appear whole or not at all: an [`Output`] writes into a temporary file beside its
//! destination and renames it over the destination only on [`Output::commit`]; dropped uncommitted (an error
//! part-way, a panic), it removes the temporary file. So a failed command leaves no half-written `.jsonl`,
//! `.hfrec`, `.mp4` or model behind that a later `[ -s file ]` check would take for a result, and a reader
//! never sees a file being written. [`write_atomic`] does the same for bytes already in memory.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::Context;

/// A file being written; see the module docs.
#[derive(Debug)]
pub struct Output {
    path: PathBuf,
    /// The temporary file; `None` when writing straight to a destination that is not a regular file
    /// (`/dev/null`, `/dev/stdout`, a pipe), which cannot be replaced by a rename.
    tmp: Option<PathBuf>,
    file: Option<BufWriter<File>>,
}

impl Output {
    /// Starts writing `path` (its folder is created if missing). A symbolic link is followed: the file it
    /// points to is replaced, not the link. A destination that exists and is not a regular file (a device,
    /// a pipe) is written to directly.
    pub fn create(path: &Path) -> anyhow::Result<Self> {
        if let Ok(meta) = std::fs::metadata(path)
            && !meta.is_file()
        {
            let file = std::fs::OpenOptions::new()
                .write(true)
                .open(path)
                .with_context(|| format!("opening {}", path.display()))?;
            return Ok(Self {
                path: path.to_path_buf(),
                tmp: None,
                file: Some(BufWriter::new(file)),
            });
        }
        let path = &std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
        let name = path
            .file_name()
            .with_context(|| format!("{} is not a file name", path.display()))?;
        let mut tmp_name = std::ffi::OsString::from(".");
        tmp_name.push(name);
        tmp_name.push(format!(".tmp-{}", std::process::id()));
        let tmp = path.with_file_name(tmp_name);
        let file = File::create(&tmp).with_context(|| {
            format!(
                "writing {} (its temporary file {})",
                path.display(),
                tmp.display()
            )
        })?;
        Ok(Self {
            path: path.to_path_buf(),
            tmp: Some(tmp),
            file: Some(BufWriter::new(file)),
        })
    }

    /// Where the file will be once committed.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Flushes, syncs and renames the file to its destination. On failure (a full disk, a destination
    /// that cannot be replaced) the temporary file is removed and the destination is untouched.
    pub fn commit(mut self) -> anyhow::Result<()> {
        let result = self.finish();
        if result.is_err()
            && let Some(tmp) = &self.tmp
        {
            let _ = std::fs::remove_file(tmp);
        }
        result
    }

    fn finish(&mut self) -> anyhow::Result<()> {
        let what = || format!("writing {}", self.path.display());
        let Some(w) = self.file.take() else {
            return Ok(());
        };
        let file = w
            .into_inner()
            .map_err(std::io::IntoInnerError::into_error)
            .with_context(what)?;
        match &self.tmp {
            Some(tmp) => {
                file.sync_all().with_context(what)?;
                std::fs::rename(tmp, &self.path).with_context(what)
            }
            None => Ok(()),
        }
    }
}

impl Write for Output {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match &mut self.file {
            Some(f) => f.write(buf),
            None => Err(std::io::Error::other("output already committed")),
        }
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.file.as_mut().map_or(Ok(()), Write::flush)
    }
}

impl std::io::Seek for Output {
    fn seek(&mut self, pos: std::io::SeekFrom) -> std::io::Result<u64> {
        match &mut self.file {
            Some(f) => f.seek(pos),
            None => Err(std::io::Error::other("output already committed")),
        }
    }
}

impl Drop for Output {
    fn drop(&mut self) {
        if self.file.take().is_some()
            && let Some(tmp) = &self.tmp
        {
            let _ = std::fs::remove_file(tmp);
        }
    }
}

/// Writes `bytes` to `path` whole or not at all.
pub fn write_atomic(path: &Path, bytes: impl AsRef<[u8]>) -> anyhow::Result<()> {
    let mut out = Output::create(path)?;
    out.write_all(bytes.as_ref())
        .with_context(|| format!("writing {}", path.display()))?;
    out.commit()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("holoface-output-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn a_committed_output_appears_whole_and_an_abandoned_one_not_at_all() {
        let d = dir("commit");
        let path = d.join("sub/out.jsonl");
        let mut out = Output::create(&path).unwrap();
        out.write_all(b"line 1\n").unwrap();
        assert!(!path.exists(), "nothing at the destination before the commit");
        out.commit().unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"line 1\n");

        let abandoned = d.join("sub/failed.hfrec");
        let mut out = Output::create(&abandoned).unwrap();
        out.write_all(b"half a header").unwrap();
        drop(out);
        assert!(!abandoned.exists());
        let left: Vec<_> = std::fs::read_dir(d.join("sub"))
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(
            left,
            vec![std::ffi::OsString::from("out.jsonl")],
            "no temporary file left"
        );

        write_atomic(&path, b"replaced").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"replaced");

        // A symbolic link is followed: its target is replaced, the link stays.
        let link = d.join("link.jsonl");
        std::os::unix::fs::symlink(&path, &link).unwrap();
        write_atomic(&link, b"through the link").unwrap();
        assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
        assert_eq!(std::fs::read(&path).unwrap(), b"through the link");
        // A device is written to, not replaced.
        write_atomic(Path::new("/dev/null"), b"gone").unwrap();
        assert!(!std::fs::metadata("/dev/null").unwrap().is_file());
        std::fs::remove_dir_all(&d).unwrap();
    }
}
