//! The holoface data folder and the assets found in it: the one rule every installed binary (`cargo
//! install`ed `holoface` and `holoface-server`), the C ABI and the runtime follow.
//!
//! An asset's path is, in order: the path given explicitly (an option, a config key, a function argument;
//! the server ranks its environment variables above its config file, as for all its keys), else its
//! environment variable ([`Asset::env`]), else its file in the data folder ([`data_dir`]: `$HOLOFACE_HOME`,
//! else `$XDG_DATA_HOME/holoface`, else `~/.local/share/holoface`), which `holoface setup` fills. Nothing is relative to the working directory or to a checkout; in a checkout the Makefile
//! points `HOLOFACE_HOME` at `.cache/holoface`. A missing asset's message ([`MissingAsset`]) names the
//! asset, the path, why that path was chosen and the command that fixes it.

use std::ffi::OsString;
use std::path::{Path, PathBuf};

/// Environment variable naming the data folder.
pub const HOME_ENV: &str = "HOLOFACE_HOME";

/// The data folder: `$HOLOFACE_HOME` (made absolute against the working directory if it is relative), else
/// `$XDG_DATA_HOME/holoface` (ignored unless absolute, as the XDG spec says), else
/// `~/.local/share/holoface` (it need not exist yet); `None` only when no home folder is known either.
pub fn data_dir() -> Option<PathBuf> {
    data_dir_from(&|v| std::env::var_os(v), std::env::home_dir)
}

/// [`data_dir`] over an environment lookup and a home-folder lookup (tests give their own).
fn data_dir_from(
    var: &dyn Fn(&str) -> Option<OsString>,
    home: impl FnOnce() -> Option<PathBuf>,
) -> Option<PathBuf> {
    let var = |v: &str| var(v).filter(|s| !s.is_empty()).map(PathBuf::from);
    if let Some(dir) = var(HOME_ENV) {
        return Some(std::path::absolute(&dir).unwrap_or(dir));
    }
    if let Some(xdg) = var("XDG_DATA_HOME").filter(|x| x.is_absolute()) {
        return Some(xdg.join("holoface"));
    }
    var("HOME")
        .filter(|h| h.is_absolute())
        .or_else(home)
        .map(|h| h.join(".local/share/holoface"))
}

/// One asset: what it is, its environment variable, its file name in the data folder and how it gets there.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Asset {
    /// What it is, for messages ("KRFWS model").
    pub name: &'static str,
    /// The environment variable that names it.
    pub env: &'static str,
    /// Its file name in the data folder.
    pub file: &'static str,
    /// The command that puts it into the data folder.
    pub setup: &'static str,
    /// The largest file of its kind that is read (checked before reading: `/dev/zero` or a huge file named
    /// by mistake is refused at once).
    pub max_bytes: u64,
}

/// The command that fills the data folder (the `holoface` CLI, `cargo install --path tools`).
pub const SETUP: &str = "holoface setup";

/// The ONNX Runtime shared library (from the pinned `onnxruntime` PyPI wheel).
pub const ORT_LIBRARY: Asset = Asset {
    name: "ONNX Runtime library",
    env: "ORT_DYLIB_PATH",
    file: "libonnxruntime.so.1.31.1",
    setup: SETUP,
    max_bytes: 256 << 20,
};
/// The BlazeFace short-range face detector (ONNX).
pub const DETECTOR: Asset = Asset {
    name: "face detector model",
    env: "HOLOFACE_DETECTOR_MODEL",
    file: "face_detection_front_128x128.onnx",
    setup: SETUP,
    max_bytes: 64 << 20,
};
/// The KRFWS model (the headset's local aligner).
pub const KRFWS: Asset = Asset {
    name: "KRFWS model",
    env: "HOLOFACE_KRFWS_MODEL",
    file: "krfws.bin",
    setup: SETUP,
    max_bytes: 256 << 20,
};
/// The DAN model (ONNX; the server's aligner).
pub const DAN: Asset = Asset {
    name: "DAN model",
    env: "HOLOFACE_DAN_MODEL",
    file: "dan.onnx",
    setup: SETUP,
    max_bytes: 1 << 30,
};
/// The DAN model quantised to 8 bits (`models/dan/to_int8.py`): what the server runs on a CPU with VNNI.
pub const DAN_INT8: Asset = Asset {
    name: "int8 DAN model",
    env: "HOLOFACE_DAN_INT8_MODEL",
    file: "dan.int8.onnx",
    setup: SETUP,
    max_bytes: 1 << 30,
};
/// The server's refinement cascade.
pub const REFINER: Asset = Asset {
    name: "refinement cascade model",
    env: "HOLOFACE_REFINE_MODEL",
    file: "refiner.bin",
    setup: SETUP,
    max_bytes: 512 << 20,
};
/// The CANDIDE-3 face model (third-party, free for research use, not redistributed: the user installs it).
pub const CANDIDE: Asset = Asset {
    name: "CANDIDE-3 model",
    env: "HOLOFACE_CANDIDE",
    file: "candide3.wfm",
    setup: "holoface setup --candide /path/to/candide3.wfm",
    max_bytes: 16 << 20,
};
/// The demo's sample photograph.
pub const SAMPLE: Asset = Asset {
    name: "demo sample image",
    env: "HOLOFACE_SAMPLE",
    file: "astronaut.png",
    setup: SETUP,
    max_bytes: 256 << 20,
};

impl Asset {
    /// `$env` when set and not empty, else the file in the data folder (a `$HOLOFACE_HOME/...` placeholder,
    /// which does not exist, when no data folder can be named).
    pub fn default_path(&self) -> PathBuf {
        std::env::var_os(self.env)
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
            .or_else(|| data_dir().map(|d| d.join(self.file)))
            .unwrap_or_else(|| self.placeholder())
    }

    /// Where the asset would be if there were a data folder: a path that names `$HOLOFACE_HOME`.
    fn placeholder(&self) -> PathBuf {
        Path::new("$HOLOFACE_HOME").join(self.file)
    }

    /// The error for this asset missing at `path` (no front end's option named yet: see
    /// [`MissingAsset::given_by`]).
    pub fn missing(&'static self, path: &Path) -> MissingAsset {
        MissingAsset {
            asset: self,
            path: path.to_path_buf(),
            option: None,
        }
    }

    /// The message for a missing `path`: the asset, the path, why it was looked for there (the environment
    /// variable, the data folder, or given explicitly with `option`, the front end's name for it) and the
    /// command that fixes it.
    fn not_found(&self, path: &Path, option: Option<&str>) -> String {
        self.not_found_in(path, option, std::env::var_os(self.env), data_dir())
    }

    /// [`Asset::not_found`] with the variable's value and the data folder given.
    fn not_found_in(
        &self,
        path: &Path,
        option: Option<&str>,
        from_env: Option<OsString>,
        data: Option<PathBuf>,
    ) -> String {
        let Self {
            name,
            env,
            file,
            setup,
            max_bytes: _,
        } = *self;
        let neither = match option {
            Some(o) => format!("neither {o} nor ${env} names it"),
            None => format!("no option and no ${env} names it"),
        };
        let given = match option {
            Some(o) => format!("the path given with {o}"),
            None => "the path given".to_owned(),
        };
        let shown = path.display();
        let from_env = from_env.filter(|v| !v.is_empty());
        if from_env.as_deref() == Some(path.as_os_str()) {
            return format!(
                "{name} not found at {shown} (named by ${env}); point ${env} at the file, or unset it and run \
                 `{setup}`"
            );
        }
        let folder = "$HOLOFACE_HOME, else $XDG_DATA_HOME/holoface, else ~/.local/share/holoface";
        match data {
            Some(dir) if dir.join(file) == path => format!(
                "{name} not found at {shown}: {neither}, so it is looked for in the holoface data folder {} \
                 ({folder}); run `{setup}` to put it there, or set ${env}",
                dir.display()
            ),
            None if from_env.is_none() && path.starts_with("$HOLOFACE_HOME") => format!(
                "{name} not found: {neither} and there is no data folder ({HOME_ENV}, XDG_DATA_HOME and HOME \
                 are unset); set {HOME_ENV} and run `{setup}`, or set ${env}"
            ),
            _ => format!(
                "{name} not found at {shown} ({given}); give the right path, or leave it out to use ${env} or \
                 else the data folder's copy ({folder}), which `{setup}` installs"
            ),
        }
    }
}

/// An asset that is not where it was looked for: the one "missing asset" error of every crate (the runtime's
/// `AssetError` and `DetectError`, the inference crate's `EngineError`). The message names the asset, the path, why that
/// path (given explicitly, named by its environment variable, or the data folder's default) and the command
/// that fixes it.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{}", asset.not_found(path, option.as_deref()))]
pub struct MissingAsset {
    /// Which asset (one of this module's constants).
    pub asset: &'static Asset,
    /// Where it was looked for.
    pub path: PathBuf,
    /// The front end's name for the setting that gives its path (`--dan-model`, `engine.model`,
    /// `HfOptions.krfws_model`), when the front end said: each front end names its own.
    pub option: Option<String>,
}

impl MissingAsset {
    /// Names the front end's setting for this asset, when `options` (asset, name) lists it.
    #[must_use]
    pub fn given_by(mut self, options: &[(Asset, &str)]) -> Self {
        if let Some((_, name)) = options.iter().find(|(a, _)| a == self.asset) {
            self.option = Some((*name).to_owned());
        }
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env(pairs: &'static [(&'static str, &'static str)]) -> impl Fn(&str) -> Option<OsString> {
        move |v| {
            pairs
                .iter()
                .find(|(k, _)| *k == v)
                .map(|(_, x)| OsString::from(x))
        }
    }

    #[test]
    fn the_data_folder_follows_holoface_home_then_xdg_then_home() {
        let none = || None;
        let dir = |pairs| data_dir_from(&env(pairs), none);
        assert_eq!(
            dir(&[
                ("HOLOFACE_HOME", "/srv/hf"),
                ("XDG_DATA_HOME", "/x"),
                ("HOME", "/h")
            ]),
            Some("/srv/hf".into())
        );
        assert_eq!(
            dir(&[("HOLOFACE_HOME", ""), ("XDG_DATA_HOME", "/x"), ("HOME", "/h")]),
            Some("/x/holoface".into())
        );
        // A relative XDG_DATA_HOME is ignored (XDG spec); a relative HOLOFACE_HOME is made absolute.
        assert_eq!(
            dir(&[("XDG_DATA_HOME", "rel"), ("HOME", "/h")]),
            Some("/h/.local/share/holoface".into())
        );
        let rel = dir(&[("HOLOFACE_HOME", "rel/hf")]).unwrap();
        assert!(rel.is_absolute() && rel.ends_with("rel/hf"), "{}", rel.display());
        // No HOME variable: the account's home folder; none at all: no data folder.
        assert_eq!(
            data_dir_from(&env(&[]), || Some("/home/u".into())),
            Some("/home/u/.local/share/holoface".into())
        );
        assert_eq!(dir(&[]), None);
    }

    #[test]
    fn a_missing_asset_says_why_that_path_and_what_fixes_it() {
        let data = Some(PathBuf::from("/d"));
        // Named by the variable.
        let m = KRFWS.not_found_in(Path::new("/e/k.bin"), None, Some("/e/k.bin".into()), data.clone());
        assert!(
            m.starts_with("KRFWS model not found at /e/k.bin (named by $HOLOFACE_KRFWS_MODEL)"),
            "{m}"
        );
        assert!(m.contains("unset it and run `holoface setup`"), "{m}");
        // The data folder's default.
        let m = KRFWS.not_found_in(Path::new("/d/krfws.bin"), None, None, data.clone());
        assert!(m.contains("looked for in the holoface data folder /d"), "{m}");
        assert!(m.contains("run `holoface setup` to put it there"), "{m}");
        // Given explicitly: the front end names its own setting, never another front end's.
        let m = DAN.not_found_in(
            Path::new("/x/dan.onnx"),
            Some("--dan-model"),
            Some("/other".into()),
            data.clone(),
        );
        assert!(m.contains("(the path given with --dan-model)"), "{m}");
        let m = DAN.not_found_in(Path::new("/x/dan.onnx"), None, None, data.clone());
        assert!(m.contains("(the path given)"), "{m}");
        let named = DAN
            .missing(Path::new("/x/dan.onnx"))
            .given_by(&[(KRFWS, "--krfws-model"), (DAN, "engine.model")]);
        assert_eq!(named.option.as_deref(), Some("engine.model"));
        let m = KRFWS.not_found_in(Path::new("/d/krfws.bin"), Some("krfws_model"), None, data.clone());
        assert!(
            m.contains("neither krfws_model nor $HOLOFACE_KRFWS_MODEL names it"),
            "{m}"
        );
        // CANDIDE-3 is the user's to install.
        let m = CANDIDE.not_found_in(Path::new("/d/candide3.wfm"), None, None, data);
        assert!(
            m.contains("holoface setup --candide /path/to/candide3.wfm"),
            "{m}"
        );
        // No data folder at all.
        let m = SAMPLE.not_found_in(&SAMPLE.placeholder(), None, None, None);
        assert!(
            m.contains("there is no data folder") && m.contains("set HOLOFACE_HOME"),
            "{m}"
        );
    }
}
