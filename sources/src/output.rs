//! Files the tools write. Two kinds:
//!
//! * **Whole or nothing** ([`Output::create`], [`write_atomic`]): a result computed from a finished input (a
//!   report, a model, the lines of a video file) is written into a temporary file beside its destination
//!   (`NAME.partial-PID`, a visible name that says what it is) and renamed over it only on [`Output::commit`];
//!   dropped uncommitted (an error part-way, a panic), the temporary file is removed. So a failed command leaves
//!   no half-written `.jsonl`, `.hfrec`, `.mp4` or model behind that a later `[ -s file ]` check would take for
//!   a result.
//! * **A journal** ([`Output::live`]): what a live run (a camera on standard input) sees, written under its real
//!   name (or to standard output for `-`) one whole frame at a time and flushed per frame
//!   ([`Output::end_frame`]), so that `tail -f`, a pipe reader and a crash all see every frame written so far.
//!
//! A temporary file another run left (killed outright, it could not remove it) is never removed here: the next
//! command writing the same destination names it on standard error and leaves it to the user.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use crate::SourceError;
use crate::error::Context as _;

/// The temporary files of the whole-or-nothing [`Output`]s a process has not committed yet. A signal that ends
/// the process at once skips every destructor, so the binary makes one registry, hands it to each
/// [`Output::create`] and to its signal handler, which removes what is left ([`Temporaries::remove_all`]); no
/// library keeps the list in a global. Clones share one list.
#[derive(Clone, Debug, Default)]
pub struct Temporaries(std::sync::Arc<std::sync::Mutex<Vec<PathBuf>>>);

impl Temporaries {
    /// An empty registry.
    pub fn new() -> Self {
        Self::default()
    }

    fn list(&self) -> std::sync::MutexGuard<'_, Vec<PathBuf>> {
        self.0.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn add(&self, tmp: &Path) {
        self.list().push(tmp.to_path_buf());
    }

    fn forget(&self, tmp: &Path) {
        self.list().retain(|p| p != tmp);
    }

    /// Removes the temporary files of every [`Output`] not yet committed (an interrupted command's); returns
    /// how many there were.
    pub fn remove_all(&self) -> usize {
        let mut list = self.list();
        for p in list.iter() {
            let _ = std::fs::remove_file(p);
        }
        let n = list.len();
        list.clear();
        n
    }
}

/// The temporary-file name of `name` written by process `pid`: visible, so that what a killed run leaves is
/// found and says that it is unfinished.
fn tmp_name(name: &std::ffi::OsStr, pid: u32) -> std::ffi::OsString {
    let mut tmp = name.to_os_string();
    tmp.push(format!(".partial-{pid}"));
    tmp
}

/// The temporary files that processes no longer running left for `path` (killed outright, they could not remove
/// them): kept, since they may hold all a killed run wrote; [`Output::create`] names them.
pub fn stale_temporaries(path: &Path) -> Vec<PathBuf> {
    let (Some(dir), Some(name)) = (path.parent(), path.file_name()) else {
        return Vec::new();
    };
    let dir = if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    };
    let prefix = tmp_name(name, 0);
    let prefix = prefix.to_string_lossy();
    let prefix = prefix.trim_end_matches('0');
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut found: Vec<PathBuf> = entries
        .flatten()
        .filter(|e| {
            let file = e.file_name();
            let file = file.to_string_lossy();
            file.strip_prefix(prefix)
                .and_then(|p| p.parse::<u32>().ok())
                .is_some_and(|pid| {
                    pid != std::process::id() && !Path::new("/proc").join(pid.to_string()).exists()
                })
        })
        .map(|e| e.path())
        .collect();
    found.sort();
    found
}

/// A file being written; see the module docs.
#[derive(Debug)]
pub struct Output {
    path: PathBuf,
    /// The temporary file; `None` when writing straight to a destination that is not a regular file
    /// (`/dev/null`, `/dev/stdout`, a pipe), which cannot be replaced by a rename.
    tmp: Option<PathBuf>,
    file: Option<BufWriter<File>>,
    /// Where the temporary file is registered until it is committed or dropped.
    temporaries: Temporaries,
}

impl Output {
    /// Starts writing `path` (its folder is created if missing). A symbolic link is followed: the file it
    /// points to is replaced, not the link. A destination that exists and is not a regular file (a device,
    /// a pipe) is written to directly. The temporary file is registered in `temporaries` until the output is
    /// committed or dropped.
    pub fn create(path: &Path, temporaries: &Temporaries) -> Result<Self, SourceError> {
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
                temporaries: Temporaries::new(),
            });
        }
        let path = &std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
        let name = path
            .file_name()
            .with_context(|| format!("{} is not a file name", path.display()))?;
        for stale in stale_temporaries(path) {
            let size = std::fs::metadata(&stale).map_or(0, |m| m.len());
            eprintln!(
                "note: {} ({size} bytes) was left unfinished by an earlier run that was killed; it is kept: \
                 remove it, or rename it to read what that run wrote",
                stale.display()
            );
        }
        let tmp = path.with_file_name(tmp_name(name, std::process::id()));
        temporaries.add(&tmp);
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
            temporaries: temporaries.clone(),
        })
    }

    /// Starts a journal at `path`, for a run whose source has no end (a camera): the file is created (or
    /// truncated) under its real name and written one frame at a time ([`Output::end_frame`]); `-` is standard
    /// output ([`Output::is_stdout`]: the command then prints its messages to standard error). Nothing is renamed
    /// or removed later: a stopped or killed run leaves every whole frame it wrote.
    pub fn live(path: &Path) -> Result<Self, SourceError> {
        if path == Path::new("-") {
            use std::os::fd::AsFd as _;
            let fd = std::io::stdout()
                .as_fd()
                .try_clone_to_owned()
                .context("standard output")?;
            return Ok(Self {
                path: path.to_path_buf(),
                tmp: None,
                file: Some(BufWriter::new(File::from(fd))),
                temporaries: Temporaries::new(),
            });
        }
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
        let file = File::create(path).with_context(|| format!("writing {}", path.display()))?;
        Ok(Self {
            path: path.to_path_buf(),
            tmp: None,
            file: Some(BufWriter::new(file)),
            temporaries: Temporaries::new(),
        })
    }

    /// Writes one frame's bytes whole and flushes them, so that a reader (or a crash) sees whole frames only.
    pub fn end_frame(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.write_all(bytes)?;
        self.flush()
    }

    /// Whether this is a journal on standard output (`-`).
    pub fn is_stdout(&self) -> bool {
        self.tmp.is_none() && self.path == Path::new("-")
    }

    /// Where the file will be once committed.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Flushes, syncs and renames the file to its destination. On failure (a full disk, a destination
    /// that cannot be replaced) the temporary file is removed and the destination is untouched.
    pub fn commit(mut self) -> Result<(), SourceError> {
        let result = self.finish();
        if let Some(tmp) = &self.tmp {
            if result.is_err() {
                let _ = std::fs::remove_file(tmp);
            }
            self.temporaries.forget(tmp);
        }
        result
    }

    fn finish(&mut self) -> Result<(), SourceError> {
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

/// The error with the file it happened on (a full disk must say which file could not be written).
fn name_file(path: &Path, e: std::io::Error) -> std::io::Error {
    std::io::Error::new(e.kind(), format!("writing {}: {e}", path.display()))
}

impl Write for Output {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match &mut self.file {
            Some(f) => f.write(buf).map_err(|e| name_file(&self.path, e)),
            None => Err(std::io::Error::other("output already committed")),
        }
    }

    fn flush(&mut self) -> std::io::Result<()> {
        let path = &self.path;
        self.file
            .as_mut()
            .map_or(Ok(()), |f| f.flush().map_err(|e| name_file(path, e)))
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
            self.temporaries.forget(tmp);
        }
    }
}

/// Writes `bytes` to `path` whole or not at all (the temporary file registered in `temporaries` meanwhile).
pub fn write_atomic(
    path: &Path,
    bytes: impl AsRef<[u8]>,
    temporaries: &Temporaries,
) -> Result<(), SourceError> {
    let mut out = Output::create(path, temporaries)?;
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
        let temps = Temporaries::new();
        let d = dir("commit");
        let path = d.join("sub/out.jsonl");
        let mut out = Output::create(&path, &temps).unwrap();
        out.write_all(b"line 1\n").unwrap();
        assert!(!path.exists(), "nothing at the destination before the commit");
        out.commit().unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"line 1\n");

        let abandoned = d.join("sub/failed.hfrec");
        let mut out = Output::create(&abandoned, &temps).unwrap();
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

        write_atomic(&path, b"replaced", &temps).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"replaced");

        // A symbolic link is followed: its target is replaced, the link stays.
        let link = d.join("link.jsonl");
        std::os::unix::fs::symlink(&path, &link).unwrap();
        write_atomic(&link, b"through the link", &temps).unwrap();
        assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
        assert_eq!(std::fs::read(&path).unwrap(), b"through the link");
        // A device is written to, not replaced.
        write_atomic(Path::new("/dev/null"), b"gone", &temps).unwrap();
        assert!(!std::fs::metadata("/dev/null").unwrap().is_file());
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_killed_runs_temporary_file_is_kept_and_this_runs_own_are_removed_on_interrupt() {
        let temps = Temporaries::new();
        let d = dir("interrupted");
        std::fs::create_dir_all(&d).unwrap();
        let path = d.join("o.jsonl");
        // A run killed outright left its temporary file (pid 999999999 runs nowhere): it may hold all that run
        // wrote, so it is found and kept, never removed behind the user's back.
        let dead = d.join("o.jsonl.partial-999999999");
        let live = d.join(format!("o.jsonl.partial-{}", std::process::id()));
        std::fs::write(&dead, b"half").unwrap();
        assert_eq!(stale_temporaries(&path), vec![dead.clone()]);
        let mut out = Output::create(&path, &temps).unwrap();
        assert!(dead.exists(), "another run's temporary file is kept");
        assert!(live.exists(), "this process's own temporary file is not stale");
        assert_eq!(stale_temporaries(&path), vec![dead.clone()], "ours is not stale");
        out.write_all(b"partial").unwrap();
        // Ctrl-C in a whole-or-nothing command: the handler removes this process's temporary files.
        assert_eq!(
            temps.clone().remove_all(),
            1,
            "the registry's clones share one list"
        );
        assert!(!live.exists());
        drop(out);
        assert!(dead.exists());
        // Another file's temporaries are not this file's.
        let other = d.join("p.jsonl.partial-999999999");
        std::fs::write(&other, b"x").unwrap();
        assert_eq!(stale_temporaries(&path), vec![dead]);
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_live_output_holds_every_whole_frame_under_its_name_as_it_is_written() {
        let d = dir("live");
        let path = d.join("sub/live.jsonl");
        let mut out = Output::live(&path).unwrap();
        let out_is_stdout = out.is_stdout();
        assert!(path.exists(), "under its real name from the start");
        out.end_frame(b"{\"frame\":0}\n").unwrap();
        assert_eq!(
            std::fs::read(&path).unwrap(),
            b"{\"frame\":0}\n",
            "flushed with its frame"
        );
        out.end_frame(b"{\"frame\":1}\n").unwrap();
        // Dropped without a commit (a stop, an error): nothing is removed.
        drop(out);
        assert_eq!(std::fs::read(&path).unwrap(), b"{\"frame\":0}\n{\"frame\":1}\n");
        assert!(!out_is_stdout, "a file is not standard output");
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn a_write_error_names_the_file() {
        let temps = Temporaries::new();
        // /dev/full: every write fails with "no space left on device", as on a full disk.
        let mut out = Output::create(Path::new("/dev/full"), &temps).unwrap();
        let err = out
            .write_all(&[0u8; 1 << 16])
            .and_then(|()| out.flush())
            .unwrap_err();
        assert!(err.to_string().contains("/dev/full"), "{err}");
    }
}
