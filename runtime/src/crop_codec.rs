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
        Self::Jpeg { quality: 75 }
    }
}

impl CropCodec {
    /// The wire encoding this codec produces.
    pub fn encoding(self) -> CropEncoding {
        match self {
            Self::Raw => CropEncoding::Raw,
            Self::Png => CropEncoding::Png,
            Self::Jpeg { .. } => CropEncoding::Jpeg,
        }
    }

    /// This codec for the encoding the server chose (keeping our JPEG quality).
    pub fn for_encoding(self, chosen: CropEncoding) -> Self {
        match (chosen, self) {
            (CropEncoding::Jpeg, Self::Jpeg { quality }) => Self::Jpeg { quality },
            (CropEncoding::Jpeg, _) => Self::default(),
            (CropEncoding::Png, _) => Self::Png,
            _ => Self::Raw,
        }
    }

    /// Encodes `width` x `height` gray8 `pixels`.
    pub fn encode(self, pixels: &[u8], width: u16, height: u16) -> Result<Crop, image::ImageError> {
        let (w, h) = (u32::from(width), u32::from(height));
        let data: Bytes = match self {
            Self::Raw => Bytes::copy_from_slice(pixels),
            Self::Png => {
                let mut out = Vec::with_capacity(pixels.len());
                let enc = image::codecs::png::PngEncoder::new(&mut out);
                image::ImageEncoder::write_image(enc, pixels, w, h, image::ExtendedColorType::L8)?;
                out.into()
            }
            Self::Jpeg { quality } => {
                let mut out = Vec::with_capacity(pixels.len() / 4);
                let mut enc =
                    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality.clamp(1, 100));
                enc.encode(pixels, w, h, image::ExtendedColorType::L8)?;
                out.into()
            }
        };
        Ok(Crop {
            encoding: self.encoding(),
            width,
            height,
            data,
        })
    }
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
            let crop = codec.encode(&px, 112, 112).unwrap();
            assert_eq!(crop.encoding, codec.encoding());
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
        let crop = CropCodec::Jpeg { quality: 90 }.encode(&px, 112, 112).unwrap();
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
        assert_eq!(ours.for_encoding(CropEncoding::Jpeg), ours);
        assert_eq!(ours.for_encoding(CropEncoding::Raw), CropCodec::Raw);
        assert_eq!(CropCodec::Raw.for_encoding(CropEncoding::Png), CropCodec::Png);
    }
}
