//! Image files as frames: one folder of photos read as 8-bit grayscale (the image-folder source and the
//! tools' annotated folders both list and decode through here).

use std::path::{Path, PathBuf};

use anyhow::Context;
use holoface_models::image::GrayImage;

/// Image paths (`.jpg`, `.jpeg`, `.png`) under `root`, one level of subfolders deep, sorted by name.
pub fn list_images(root: &Path) -> anyhow::Result<Vec<(String, PathBuf)>> {
    let mut out = Vec::new();
    let mut visit = |dir: &Path, prefix: &str| -> anyhow::Result<Vec<PathBuf>> {
        let mut subdirs = Vec::new();
        for entry in std::fs::read_dir(dir).with_context(|| format!("reading folder {}", dir.display()))? {
            let path = entry?.path();
            if path.is_dir() {
                subdirs.push(path);
                continue;
            }
            let ext = path
                .extension()
                .and_then(|e| e.to_str())
                .map(str::to_ascii_lowercase);
            if matches!(ext.as_deref(), Some("jpg" | "jpeg" | "png")) {
                let stem = path
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default();
                out.push((format!("{prefix}{stem}"), path));
            }
        }
        Ok(subdirs)
    };
    let subdirs = visit(root, "")?;
    for sub in subdirs {
        let name = sub
            .file_name()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        visit(&sub, &format!("{name}/"))?;
    }
    out.sort();
    Ok(out)
}

/// Reads an image file as 8-bit grayscale.
pub fn read_gray(path: &Path) -> anyhow::Result<GrayImage> {
    let img = image::open(path)
        .with_context(|| format!("decoding image {}", path.display()))?
        .to_luma8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    Ok(GrayImage::from_vec(img.into_raw(), w, h)?)
}
