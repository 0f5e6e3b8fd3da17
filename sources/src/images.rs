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

/// Reads an image file as 8-bit grayscale. A file that is not a whole image (a JPEG without its end-of-image
/// marker, a PNG cut short, an unknown format) is an error naming the file: decoders otherwise fill a
/// truncated JPEG with grey and report success.
pub fn read_gray(path: &Path) -> anyhow::Result<GrayImage> {
    let bytes = std::fs::read(path).with_context(|| format!("reading image {}", path.display()))?;
    decode_gray(&bytes).with_context(|| format!("decoding image {}", path.display()))
}

/// Decodes a whole PNG or JPEG file held in memory as 8-bit grayscale (see [`read_gray`]).
pub fn decode_gray(bytes: &[u8]) -> anyhow::Result<GrayImage> {
    let format = image::guess_format(bytes).context("not a PNG or JPEG image")?;
    if format == image::ImageFormat::Jpeg && !jpeg_is_complete(bytes) {
        anyhow::bail!(
            "truncated or corrupt JPEG: no end-of-image marker after the scan data ({} bytes)",
            bytes.len()
        );
    }
    let img = image::load_from_memory_with_format(bytes, format)?.to_luma8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    Ok(GrayImage::from_vec(img.into_raw(), w, h)?)
}

/// Walks a JPEG's marker segments (skipping each by its length, so thumbnails inside APP segments do not
/// count) and its entropy-coded scans (where 0xFF is always followed by 0x00 or a restart marker), and says
/// whether the end-of-image marker is reached.
fn jpeg_is_complete(b: &[u8]) -> bool {
    const SOI: u8 = 0xD8;
    const EOI: u8 = 0xD9;
    const SOS: u8 = 0xDA;
    if b.get(..2) != Some(&[0xFF, SOI][..]) {
        return false;
    }
    let mut i = 2;
    loop {
        // A marker: 0xFF, optional fill bytes 0xFF, then the code.
        if b.get(i) != Some(&0xFF) {
            return false;
        }
        while b.get(i) == Some(&0xFF) {
            i += 1;
        }
        let Some(&code) = b.get(i) else { return false };
        i += 1;
        match code {
            EOI => return true,
            0x01 | 0xD0..=0xD7 => continue,
            _ => {}
        }
        let Some(len) = b
            .get(i..i + 2)
            .map(|l| usize::from(u16::from_be_bytes([l[0], l[1]])))
        else {
            return false;
        };
        if len < 2 {
            return false;
        }
        i += len;
        if code == SOS {
            // Entropy-coded data up to the next marker that is not a stuffed byte or a restart.
            loop {
                let Some(&v) = b.get(i) else { return false };
                if v == 0xFF {
                    match b.get(i + 1) {
                        None => return false,
                        Some(0x00 | 0xD0..=0xD7) => i += 2,
                        Some(_) => break,
                    }
                } else {
                    i += 1;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn encoded(format: image::ImageFormat) -> Vec<u8> {
        let img = image::GrayImage::from_fn(96, 64, |x, y| image::Luma([((x * 7 + y * 3) % 251) as u8]));
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, format).unwrap();
        out.into_inner()
    }

    #[test]
    fn whole_images_decode() {
        for f in [image::ImageFormat::Jpeg, image::ImageFormat::Png] {
            let img = decode_gray(&encoded(f)).unwrap();
            assert_eq!((img.width(), img.height()), (96, 64));
        }
        // Trailing bytes after the end-of-image marker are tolerated, as decoders do.
        let mut jpeg = encoded(image::ImageFormat::Jpeg);
        jpeg.extend_from_slice(b"trailing");
        assert!(decode_gray(&jpeg).is_ok());
    }

    #[test]
    fn truncated_images_are_errors() {
        for f in [image::ImageFormat::Jpeg, image::ImageFormat::Png] {
            let whole = encoded(f);
            for cut in [16, whole.len() / 4, whole.len() / 2, whole.len() * 9 / 10] {
                assert!(
                    decode_gray(&whole[..cut]).is_err(),
                    "{f:?} cut at {cut} of {} decoded",
                    whole.len()
                );
            }
        }
        // A JPEG missing only its last byte has lost its end-of-image marker.
        let jpeg = encoded(image::ImageFormat::Jpeg);
        let err = decode_gray(&jpeg[..jpeg.len() - 1])
            .err()
            .map(|e| format!("{e:#}"));
        assert!(err.is_some_and(|e| e.contains("truncated")));
        assert!(decode_gray(b"not an image").is_err());
        assert!(decode_gray(&[]).is_err());
    }

    #[test]
    fn a_truncated_file_is_named() {
        let dir = std::env::temp_dir().join(format!("holoface-images-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("cut.jpg");
        let whole = encoded(image::ImageFormat::Jpeg);
        std::fs::write(&path, &whole[..whole.len() / 2]).unwrap();
        let err = format!("{:#}", read_gray(&path).unwrap_err());
        assert!(err.contains("cut.jpg") && err.contains("truncated"), "{err}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
