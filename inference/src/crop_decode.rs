//! The one crop decoder: what the alignment server feeds its engine and what the client (and the tools that
//! measure a codec's cost) compute as "what the server sees". Hardened for bytes from the network: the
//! decoder may allocate no more than the declared crop needs (the protocol caps the declared size), and the
//! decoded image must have exactly the declared size.

use std::io::Cursor;

use bytes::Bytes;
use holoface_protocol::{Crop, CropEncoding};

/// The most a PNG/JPEG decoder may allocate for one crop (a 1024 x 1024 grey crop is 1 MiB; decoders need
/// some scratch beyond the pixels).
pub const MAX_DECODE_ALLOC: u64 = 4 * 1024 * 1024;

/// Why a crop's payload is not an image of its declared size.
#[derive(Debug, thiserror::Error, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum CropDecodeError {
    /// The PNG/JPEG payload did not decode within the limits.
    #[error("{encoding} crop does not decode: {reason}")]
    Decode {
        /// The declared encoding.
        encoding: &'static str,
        /// The decoder's message.
        reason: String,
    },
    /// The payload decoded to another size than the crop declares.
    #[error("crop declares {declared:?} but decodes to {decoded:?}")]
    Size {
        /// Width and height the crop declares.
        declared: (u16, u16),
        /// Width and height of the decoded image.
        decoded: (u32, u32),
    },
}

/// The crop's grey pixels, row-major, `width * height` bytes. A raw crop is returned as is (the protocol
/// decoder already checked its length); PNG and JPEG are decoded as 8-bit grey.
pub fn decode_crop(crop: &Crop) -> Result<Bytes, CropDecodeError> {
    let (format, name) = match crop.encoding {
        CropEncoding::Raw => return Ok(crop.data.clone()),
        CropEncoding::Png => (image::ImageFormat::Png, "PNG"),
        CropEncoding::Jpeg => (image::ImageFormat::Jpeg, "JPEG"),
    };
    let fail = |e: image::ImageError| CropDecodeError::Decode {
        encoding: name,
        reason: e.to_string(),
    };
    let mut reader = image::ImageReader::with_format(Cursor::new(&crop.data[..]), format);
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(u32::from(crop.width));
    limits.max_image_height = Some(u32::from(crop.height));
    limits.max_alloc = Some(MAX_DECODE_ALLOC);
    reader.limits(limits);
    let img = reader.decode().map_err(fail)?.into_luma8();
    if img.width() != u32::from(crop.width) || img.height() != u32::from(crop.height) {
        return Err(CropDecodeError::Size {
            declared: (crop.width, crop.height),
            decoded: (img.width(), img.height()),
        });
    }
    Ok(Bytes::from(img.into_raw()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn png(w: u32, h: u32, v: u8) -> Vec<u8> {
        let mut out = Vec::new();
        image::GrayImage::from_pixel(w, h, image::Luma([v]))
            .write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png)
            .unwrap();
        out
    }

    fn crop(encoding: CropEncoding, w: u16, h: u16, data: Vec<u8>) -> Crop {
        Crop {
            encoding,
            width: w,
            height: h,
            data: Bytes::from(data),
        }
    }

    #[test]
    fn decodes_raw_png_and_jpeg() {
        assert_eq!(&decode_crop(&Crop::raw(4, 4, vec![9; 16])).unwrap()[..], &[9; 16]);
        assert_eq!(
            &decode_crop(&crop(CropEncoding::Png, 4, 4, png(4, 4, 7))).unwrap()[..],
            &[7; 16]
        );
        let mut jpeg = Vec::new();
        image::GrayImage::from_pixel(8, 8, image::Luma([100]))
            .write_to(&mut Cursor::new(&mut jpeg), image::ImageFormat::Jpeg)
            .unwrap();
        let px = decode_crop(&crop(CropEncoding::Jpeg, 8, 8, jpeg)).unwrap();
        assert_eq!(px.len(), 64);
        assert!(px.iter().all(|&p| p.abs_diff(100) <= 2));
    }

    #[test]
    fn a_payload_of_another_size_or_garbage_is_refused() {
        // Smaller than declared: decodes, but is not the crop it claims to be.
        let e = decode_crop(&crop(CropEncoding::Png, 8, 8, png(4, 4, 7))).unwrap_err();
        assert!(matches!(e, CropDecodeError::Size { decoded: (4, 4), .. }), "{e}");
        // Larger than declared: refused by the limits before the pixels are allocated.
        let e = decode_crop(&crop(CropEncoding::Png, 4, 4, png(64, 64, 7))).unwrap_err();
        assert!(matches!(e, CropDecodeError::Decode { .. }), "{e}");
        let e = decode_crop(&crop(CropEncoding::Jpeg, 4, 4, vec![0xff, 0xd8, 1, 2, 3])).unwrap_err();
        assert!(e.to_string().starts_with("JPEG crop does not decode"), "{e}");
    }
}
