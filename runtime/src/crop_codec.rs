//! Crop encodings on the client side: what goes on the wire for a 112x112 gray crop.

use bytes::Bytes;
use holoface_protocol::{Crop, CropEncoding};

/// A crop encoding with its client-side settings.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CropCodec {
    /// Uncompressed gray8 (12,544 bytes per 112x112 crop).
    Raw,
    /// Lossless PNG.
    Png,
    /// Baseline JPEG at this quality (1..=100).
    Jpeg {
        /// libjpeg-style quality.
        quality: u8,
    },
}

impl Default for CropCodec {
    /// [`crate::defaults::CROP_ENCODING`]: JPEG q75.
    fn default() -> Self {
        Self::Jpeg {
            quality: crate::defaults::CROP_JPEG_QUALITY,
        }
    }
}

// What a codec does is kept in free functions, not methods: `CropCodec` is an option an app names, and the wire
// types (`Crop`, `CropEncoding`) and the image crate's error stay out of the app's API.

/// The wire encoding `codec` produces.
pub fn wire_encoding(codec: CropCodec) -> CropEncoding {
    match codec {
        CropCodec::Raw => CropEncoding::Raw,
        CropCodec::Png => CropEncoding::Png,
        CropCodec::Jpeg { .. } => CropEncoding::Jpeg,
    }
}

/// `codec` for the encoding the server chose (keeping our JPEG quality).
pub fn for_encoding(codec: CropCodec, chosen: CropEncoding) -> CropCodec {
    match (chosen, codec) {
        (CropEncoding::Jpeg, CropCodec::Jpeg { quality }) => CropCodec::Jpeg { quality },
        (CropEncoding::Jpeg, _) => CropCodec::default(),
        (CropEncoding::Png, _) => CropCodec::Png,
        _ => CropCodec::Raw,
    }
}

/// Encodes `width` x `height` gray8 `pixels` with `codec`.
pub fn encode(codec: CropCodec, pixels: &[u8], width: u16, height: u16) -> Result<Crop, image::ImageError> {
    let (w, h) = (u32::from(width), u32::from(height));
    let data: Bytes = match codec {
        CropCodec::Raw => Bytes::copy_from_slice(pixels),
        CropCodec::Png => {
            let mut out = Vec::with_capacity(pixels.len());
            let enc = image::codecs::png::PngEncoder::new(&mut out);
            image::ImageEncoder::write_image(enc, pixels, w, h, image::ExtendedColorType::L8)?;
            out.into()
        }
        CropCodec::Jpeg { quality } => {
            let mut out = Vec::with_capacity(pixels.len() / 4);
            let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality.clamp(1, 100));
            enc.encode(pixels, w, h, image::ExtendedColorType::L8)?;
            out.into()
        }
    };
    Ok(Crop {
        encoding: wire_encoding(codec),
        width,
        height,
        data,
    })
}

impl std::str::FromStr for CropCodec {
    type Err = String;

    /// `raw`, `png`, `jpeg` (quality 75) or `jpeg:Q`.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "raw" => Ok(Self::Raw),
            "png" => Ok(Self::Png),
            "jpeg" | "jpg" => Ok(Self::default()),
            _ => match s.strip_prefix("jpeg:").map(str::parse::<u8>) {
                Some(Ok(q)) if (1..=100).contains(&q) => Ok(Self::Jpeg { quality: q }),
                _ => Err(format!(
                    "unknown crop encoding {s:?}: use raw, png, jpeg or jpeg:1..100"
                )),
            },
        }
    }
}

impl std::fmt::Display for CropCodec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Raw => f.write_str("raw"),
            Self::Png => f.write_str("png"),
            Self::Jpeg { quality } => write!(f, "jpeg:{quality}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_is_the_documented_default() {
        assert_eq!(
            crate::defaults::CROP_ENCODING.parse::<CropCodec>(),
            Ok(CropCodec::default())
        );
        assert_eq!(CropCodec::default().to_string(), crate::defaults::CROP_ENCODING);
    }

    fn pattern() -> Vec<u8> {
        (0..112 * 112)
            .map(|i| ((i % 112) * 2 + (i / 112)) as u8)
            .collect()
    }

    #[test]
    fn lossless_codecs_round_trip_exactly() {
        let px = pattern();
        for codec in [CropCodec::Raw, CropCodec::Png] {
            let crop = encode(codec, &px, 112, 112).unwrap();
            assert_eq!(crop.encoding, wire_encoding(codec));
            assert_eq!(
                holoface_inference::decode_crop(&crop).unwrap().to_vec(),
                px,
                "{codec}"
            );
        }
    }

    #[test]
    fn jpeg_is_smaller_and_close() {
        let px = pattern();
        let crop = encode(CropCodec::Jpeg { quality: 90 }, &px, 112, 112).unwrap();
        assert!(crop.data.len() < px.len() / 3, "{} bytes", crop.data.len());
        let back = holoface_inference::decode_crop(&crop).unwrap().to_vec();
        let mae: f64 = back
            .iter()
            .zip(&px)
            .map(|(a, b)| f64::from(a.abs_diff(*b)))
            .sum::<f64>()
            / px.len() as f64;
        assert!(mae < 3.0, "mean abs error {mae}");
    }

    #[test]
    fn parses_and_prints() {
        for s in ["raw", "png", "jpeg:75"] {
            assert_eq!(s.parse::<CropCodec>().unwrap().to_string(), s);
        }
        assert_eq!("jpeg".parse::<CropCodec>().unwrap(), CropCodec::default());
        assert!("jpeg:0".parse::<CropCodec>().is_err());
        assert!("webp".parse::<CropCodec>().is_err());
    }

    #[test]
    fn follows_the_servers_choice() {
        let ours = CropCodec::Jpeg { quality: 70 };
        assert_eq!(for_encoding(ours, CropEncoding::Jpeg), ours);
        assert_eq!(for_encoding(ours, CropEncoding::Raw), CropCodec::Raw);
        assert_eq!(for_encoding(CropCodec::Raw, CropEncoding::Png), CropCodec::Png);
    }
}
