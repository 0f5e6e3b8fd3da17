//! Bounded reads of the files an operator or a user names (models, CANDIDE-3, pose sidecars, token files,
//! configs): the kind of file and its size are checked before a byte is read, and the read itself stops
//! past the bound (a file that grows while it is read, or `/dev/zero`, cannot exhaust memory).
//!
//! Every error names the path and what is wrong with it in words: a named pipe, a device, a directory, a
//! symbolic-link loop, a file too large for its kind.

use std::io::Read as _;
use std::path::{Path, PathBuf};

/// Why a named file could not be read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FileError {
    /// Nothing at that path.
    #[error("{what} {path} does not exist")]
    Missing {
        /// What the file is for ("CANDIDE-3 model").
        what: String,
        /// The path.
        path: PathBuf,
    },
    /// Something that is not a regular file.
    #[error("{what} {path} is {kind}, not a regular file")]
    NotAFile {
        /// What the file is for.
        what: String,
        /// The path.
        path: PathBuf,
        /// What it is instead.
        kind: FileKind,
    },
    /// A chain of symbolic links that never ends.
    #[error("{what} {path} is a loop of symbolic links")]
    Loop {
        /// What the file is for.
        what: String,
        /// The path.
        path: PathBuf,
    },
    /// Larger than any file of its kind.
    #[error("{what} {path} is {len} bytes, more than such a file can be ({max} bytes)")]
    TooLarge {
        /// What the file is for.
        what: String,
        /// The path.
        path: PathBuf,
        /// Its size (at least this much when it grew while being read).
        len: u64,
        /// The bound.
        max: u64,
    },
    /// Any other failure to read it.
    #[error("reading {what} {path}: {source}")]
    Io {
        /// What the file is for.
        what: String,
        /// The path.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
}

/// What a path names when it is not a regular file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum FileKind {
    /// A directory.
    Directory,
    /// A named pipe (FIFO).
    NamedPipe,
    /// A character device.
    CharDevice,
    /// A block device.
    BlockDevice,
    /// A Unix socket.
    Socket,
    /// Anything else that is not a regular file.
    Other,
}

impl FileKind {
    /// What a path of this kind is, in words ("a named pipe (FIFO)").
    pub const fn in_words(self) -> &'static str {
        match self {
            Self::Directory => "a directory",
            Self::NamedPipe => "a named pipe (FIFO)",
            Self::CharDevice => "a character device",
            Self::BlockDevice => "a block device",
            Self::Socket => "a socket",
            Self::Other => "not a file",
        }
    }

    /// What `meta` describes, or `None` for a regular file.
    pub fn of(meta: &std::fs::Metadata) -> Option<Self> {
        use std::os::unix::fs::FileTypeExt as _;
        let t = meta.file_type();
        if t.is_file() {
            None
        } else if t.is_dir() {
            Some(Self::Directory)
        } else if t.is_fifo() {
            Some(Self::NamedPipe)
        } else if t.is_char_device() {
            Some(Self::CharDevice)
        } else if t.is_block_device() {
            Some(Self::BlockDevice)
        } else if t.is_socket() {
            Some(Self::Socket)
        } else {
            Some(Self::Other)
        }
    }
}

impl std::fmt::Display for FileKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.in_words())
    }
}

/// The metadata of a regular file at `path` (links followed), or why there is none.
pub fn regular_file(path: &Path, what: &str) -> Result<std::fs::Metadata, FileError> {
    let meta = std::fs::metadata(path).map_err(|source| match source.kind() {
        std::io::ErrorKind::NotFound => FileError::Missing {
            what: what.to_owned(),
            path: path.to_owned(),
        },
        // ELOOP: too many levels of symbolic links.
        _ if source.raw_os_error() == Some(40) => FileError::Loop {
            what: what.to_owned(),
            path: path.to_owned(),
        },
        _ => FileError::Io {
            what: what.to_owned(),
            path: path.to_owned(),
            source,
        },
    })?;
    if let Some(kind) = FileKind::of(&meta) {
        return Err(FileError::NotAFile {
            what: what.to_owned(),
            path: path.to_owned(),
            kind,
        });
    }
    Ok(meta)
}

/// Reads the regular file at `path` whole when it holds at most `max` bytes.
pub fn read_bounded(path: &Path, max: u64, what: &str) -> Result<Vec<u8>, FileError> {
    let meta = regular_file(path, what)?;
    let too_large = |len| FileError::TooLarge {
        what: what.to_owned(),
        path: path.to_owned(),
        len,
        max,
    };
    if meta.len() > max {
        return Err(too_large(meta.len()));
    }
    let io = |source| FileError::Io {
        what: what.to_owned(),
        path: path.to_owned(),
        source,
    };
    let file = std::fs::File::open(path).map_err(io)?;
    let mut bytes = Vec::with_capacity(usize::try_from(meta.len()).unwrap_or(0));
    file.take(max + 1).read_to_end(&mut bytes).map_err(io)?;
    if bytes.len() as u64 > max {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

/// [`read_bounded`] as UTF-8 text.
pub fn read_text_bounded(path: &Path, max: u64, what: &str) -> Result<String, FileError> {
    let bytes = read_bounded(path, max, what)?;
    String::from_utf8(bytes).map_err(|e| FileError::Io {
        what: what.to_owned(),
        path: path.to_owned(),
        source: std::io::Error::new(std::io::ErrorKind::InvalidData, e.utf8_error()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("holoface-files-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn devices_pipes_loops_and_large_files_get_their_own_words() {
        let d = dir("kinds");
        // /dev/zero would never end: it is refused as a device before a byte is read.
        let err = read_bounded(Path::new("/dev/zero"), 1 << 20, "CANDIDE-3 model").unwrap_err();
        assert!(err.to_string().contains("a character device"), "{err}");
        let fifo = d.join("pipe");
        assert!(
            std::process::Command::new("mkfifo")
                .arg(&fifo)
                .status()
                .unwrap()
                .success()
        );
        let err = read_bounded(&fifo, 1 << 20, "pose file").unwrap_err();
        assert!(err.to_string().contains("named pipe"), "{err}");
        let a = d.join("a");
        std::os::unix::fs::symlink(d.join("b"), &a).unwrap();
        std::os::unix::fs::symlink(&a, d.join("b")).unwrap();
        let err = read_bounded(&a, 1 << 20, "config").unwrap_err();
        assert!(matches!(err, FileError::Loop { .. }), "{err}");
        assert!(err.to_string().contains("loop of symbolic links"), "{err}");
        let err = read_bounded(&d, 1 << 20, "config").unwrap_err();
        assert!(err.to_string().contains("a directory"), "{err}");
        let err = read_bounded(&d.join("none"), 1 << 20, "config").unwrap_err();
        assert!(err.to_string().contains("does not exist"), "{err}");
        // A sparse 2 GB file is refused from its size, at once.
        let big = d.join("sparse");
        std::fs::File::create(&big).unwrap().set_len(2 << 30).unwrap();
        let t0 = std::time::Instant::now();
        let err = read_bounded(&big, 1 << 20, "tokens file").unwrap_err();
        assert!(
            matches!(err, FileError::TooLarge { len, .. } if len == 2 << 30),
            "{err}"
        );
        assert!(t0.elapsed() < std::time::Duration::from_secs(1));
        std::fs::write(d.join("ok"), "fine").unwrap();
        assert_eq!(read_text_bounded(&d.join("ok"), 4, "config").unwrap(), "fine");
        assert!(read_bounded(&d.join("ok"), 3, "config").is_err());
        let _ = std::fs::remove_dir_all(&d);
    }
}
