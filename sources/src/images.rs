//! Image files as frames: one folder of photos read as 8-bit grayscale (the image-folder source and the
//! tools' annotated folders both list and decode through here).

use std::path::{Path, PathBuf};

use holoface_models::image::GrayImage;

use crate::error::Context as _;
pub use crate::error::MAX_IMAGE_PIXELS_ENV;
use crate::{ImageError, SourceError};

/// The largest image (or video frame) any reader decodes, in pixels: 40 megapixels takes an 8K frame (33
/// megapixels) and keeps one decode well under 1 GiB even as 16-bit RGBA (8 bytes a pixel, 320 MB).
pub const DEFAULT_MAX_IMAGE_PIXELS: u64 = 40_000_000;

/// The image-size limit in force: `$HOLOFACE_MAX_IMAGE_PIXELS` when it is a positive number, else
/// [`DEFAULT_MAX_IMAGE_PIXELS`].
pub fn max_image_pixels() -> u64 {
    std::env::var(MAX_IMAGE_PIXELS_ENV)
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .filter(|&n| n > 0)
        .unwrap_or(DEFAULT_MAX_IMAGE_PIXELS)
}

/// Refuses a `width` x `height` image over [`max_image_pixels`] before anything is allocated for it; the
/// message gives the size and the limit (the caller's context names the file and the frame).
pub fn check_image_size(width: u64, height: u64) -> Result<(), ImageError> {
    let limit = max_image_pixels();
    if width.saturating_mul(height) > limit {
        return Err(ImageError::TooLarge { width, height, limit });
    }
    Ok(())
}

/// Image paths (`.jpg`, `.jpeg`, `.png`) under `root`, one level of subfolders deep, sorted by name.
pub fn list_images(root: &Path) -> Result<Vec<(String, PathBuf)>, SourceError> {
    let mut out = Vec::new();
    let mut visit = |dir: &Path, prefix: &str| -> Result<Vec<PathBuf>, SourceError> {
        let mut subdirs = Vec::new();
        let folder = || format!("reading folder {}", dir.display());
        for entry in std::fs::read_dir(dir).with_context(folder)? {
            let path = entry.with_context(folder)?.path();
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
pub fn read_gray(path: &Path) -> Result<GrayImage, SourceError> {
    // No compressed image of the largest allowed size needs more bytes than its raw 16-bit RGBA pixels:
    // a bigger file is refused before it is read into memory.
    let size = std::fs::metadata(path)
        .with_context(|| format!("reading image {}", path.display()))?
        .len();
    let most = max_image_pixels().saturating_mul(8).saturating_add(1 << 20);
    if size > most {
        return Err(ImageError::FileTooLarge {
            path: path.to_path_buf(),
            len: size,
            most,
        }
        .into());
    }
    let bytes = std::fs::read(path).with_context(|| format!("reading image {}", path.display()))?;
    decode_gray(&bytes).with_context(|| format!("decoding image {}", path.display()))
}

/// Decodes a whole PNG or JPEG file held in memory as 8-bit grayscale (see [`read_gray`]).
pub fn decode_gray(bytes: &[u8]) -> Result<GrayImage, ImageError> {
    let format = image::guess_format(bytes).map_err(|_| ImageError::NotAnImage)?;
    if format == image::ImageFormat::Jpeg && !jpeg_is_complete(bytes) {
        return Err(ImageError::TruncatedJpeg { len: bytes.len() });
    }
    // The header's size is checked before the decoder allocates anything for the pixels, and the decoder
    // may allocate no more than the largest allowed image needs (16-bit RGBA, 8 bytes a pixel).
    let header = image::ImageReader::with_format(std::io::Cursor::new(bytes), format);
    let (w, h) = header.into_dimensions()?;
    check_image_size(u64::from(w), u64::from(h))?;
    let mut reader = image::ImageReader::with_format(std::io::Cursor::new(bytes), format);
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(max_image_pixels().saturating_mul(8).saturating_add(1 << 20));
    reader.limits(limits);
    let img = reader.decode()?.to_luma8();
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

    /// A PNG whose header declares `w` x `h` grey pixels, with a token IDAT: what a 389 KB file saying
    /// 20000 x 20000 looks like to a decoder before it allocates.
    pub(crate) fn png_declaring(w: u32, h: u32) -> Vec<u8> {
        fn chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
            out.extend_from_slice(&u32::try_from(data.len()).unwrap().to_be_bytes());
            let start = out.len();
            out.extend_from_slice(kind);
            out.extend_from_slice(data);
            let crc = crc32fast::hash(&out[start..]);
            out.extend_from_slice(&crc.to_be_bytes());
        }
        let mut out = vec![137, 80, 78, 71, 13, 10, 26, 10];
        let mut ihdr = Vec::new();
        ihdr.extend_from_slice(&w.to_be_bytes());
        ihdr.extend_from_slice(&h.to_be_bytes());
        ihdr.extend_from_slice(&[8, 0, 0, 0, 0]);
        chunk(&mut out, b"IHDR", &ihdr);
        chunk(
            &mut out,
            b"IDAT",
            &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01],
        );
        chunk(&mut out, b"IEND", &[]);
        out
    }

    #[test]
    fn an_image_over_the_size_limit_is_refused_before_it_is_decoded() {
        let err = format!("{:#}", decode_gray(&png_declaring(20_000, 20_000)).unwrap_err());
        assert!(
            err.contains(
                "20000 x 20000 pixels (400.0 megapixels) is over the image-size limit of 40.0 megapixels"
            ),
            "{err}"
        );
        let path = std::env::temp_dir().join(format!("holoface-huge-{}.png", std::process::id()));
        std::fs::write(&path, png_declaring(20_000, 20_000)).unwrap();
        let err = format!("{:#}", read_gray(&path).unwrap_err());
        assert!(
            err.contains(&path.display().to_string()) && err.contains("image-size limit"),
            "{err}"
        );
        std::fs::remove_file(&path).unwrap();
        // Within the limit, the size check passes and the decoder reports the token pixel data.
        let err = format!("{:#}", decode_gray(&png_declaring(64, 64)).unwrap_err());
        assert!(!err.contains("limit"), "{err}");
    }

    #[test]
    fn y4m_frames_over_the_size_limit_are_refused() {
        let err = format!(
            "{:#}",
            crate::y4m::Y4mHeader::parse(b"YUV4MPEG2 W16384 H16384 F30:1 Cmono").unwrap_err()
        );
        assert!(err.contains("268.4 megapixels") && err.contains("limit"), "{err}");
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
