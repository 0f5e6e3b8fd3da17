//! Image types, kept apart from the operations on them (kornia-style).

use thiserror::Error;

/// Errors building an image view.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum ImageError {
    /// The buffer is smaller than `stride · (height − 1) + width`.
    #[error("image buffer holds {actual} bytes, {width}x{height} with stride {stride} needs {required}")]
    BufferTooSmall {
        /// Width in pixels.
        width: usize,
        /// Height in pixels.
        height: usize,
        /// Row stride in bytes.
        stride: usize,
        /// Bytes needed.
        required: usize,
        /// Bytes given.
        actual: usize,
    },
    /// Width or height is zero, or the stride is smaller than the width.
    #[error("invalid image geometry {width}x{height} with stride {stride}")]
    BadGeometry {
        /// Width in pixels.
        width: usize,
        /// Height in pixels.
        height: usize,
        /// Row stride in bytes.
        stride: usize,
    },
}

/// A borrowed 8-bit grayscale image: `data[y * stride + x]`.
#[derive(Clone, Copy, Debug)]
pub struct GrayView<'a> {
    data: &'a [u8],
    width: usize,
    height: usize,
    stride: usize,
}

impl<'a> GrayView<'a> {
    /// Borrows `data` as a `width`×`height` image with rows `stride` bytes apart.
    pub fn new(data: &'a [u8], width: usize, height: usize, stride: usize) -> Result<Self, ImageError> {
        if width == 0 || height == 0 || stride < width {
            return Err(ImageError::BadGeometry {
                width,
                height,
                stride,
            });
        }
        let required = stride * (height - 1) + width;
        if data.len() < required {
            return Err(ImageError::BufferTooSmall {
                width,
                height,
                stride,
                required,
                actual: data.len(),
            });
        }
        Ok(Self {
            data,
            width,
            height,
            stride,
        })
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }
    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }
    /// Row stride in bytes.
    pub fn stride(&self) -> usize {
        self.stride
    }
    /// The underlying bytes.
    pub fn data(&self) -> &'a [u8] {
        self.data
    }
    /// Pixel at `(x, y)`, or `None` outside the image.
    #[inline]
    pub fn get(&self, x: usize, y: usize) -> Option<u8> {
        if x < self.width && y < self.height {
            self.data.get(y * self.stride + x).copied()
        } else {
            None
        }
    }
    /// Row `y` (`width` bytes), or `None` outside the image.
    #[inline]
    pub fn row(&self, y: usize) -> Option<&'a [u8]> {
        if y >= self.height {
            return None;
        }
        self.data.get(y * self.stride..y * self.stride + self.width)
    }
}

/// An owned 8-bit grayscale image with tightly packed rows.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct GrayImage {
    /// Pixels, row-major, `width · height` bytes.
    data: Vec<u8>,
    width: usize,
    height: usize,
}

impl GrayImage {
    /// Wraps packed pixels.
    pub fn from_vec(data: Vec<u8>, width: usize, height: usize) -> Result<Self, ImageError> {
        GrayView::new(&data, width, height, width)?;
        if data.len() != width * height {
            return Err(ImageError::BufferTooSmall {
                width,
                height,
                stride: width,
                required: width * height,
                actual: data.len(),
            });
        }
        Ok(Self { data, width, height })
    }

    /// A black image.
    pub fn zeros(width: usize, height: usize) -> Self {
        Self {
            data: vec![0; width * height],
            width,
            height,
        }
    }

    /// Borrowed view.
    pub fn view(&self) -> GrayView<'_> {
        GrayView {
            data: &self.data,
            width: self.width,
            height: self.height,
            stride: self.width,
        }
    }
    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }
    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }
    /// Pixels.
    pub fn as_bytes(&self) -> &[u8] {
        &self.data
    }
    /// Mutable pixels.
    pub fn as_bytes_mut(&mut self) -> &mut [u8] {
        &mut self.data
    }
    /// Gives back the pixel buffer.
    pub fn into_vec(self) -> Vec<u8> {
        self.data
    }
    /// The image flipped left to right.
    pub fn mirrored(&self) -> Self {
        let mut data = Vec::with_capacity(self.data.len());
        for row in self.data.chunks_exact(self.width.max(1)) {
            data.extend(row.iter().rev());
        }
        Self { data, ..*self }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn view_checks_geometry() {
        let buf = [0u8; 10];
        assert!(GrayView::new(&buf, 3, 3, 3).is_ok());
        assert!(matches!(
            GrayView::new(&buf, 4, 3, 4),
            Err(ImageError::BufferTooSmall { .. })
        ));
        assert!(matches!(
            GrayView::new(&buf, 4, 2, 3),
            Err(ImageError::BadGeometry { .. })
        ));
        assert!(matches!(
            GrayView::new(&buf, 0, 2, 3),
            Err(ImageError::BadGeometry { .. })
        ));
        let v = GrayView::new(&buf, 3, 3, 3).unwrap();
        assert_eq!(v.get(3, 0), None);
        assert_eq!(v.row(3), None);
    }

    #[test]
    fn mirrored_flips_each_row() {
        let img = GrayImage::from_vec(vec![1, 2, 3, 4, 5, 6], 3, 2).unwrap();
        let m = img.mirrored();
        assert_eq!((m.width(), m.height()), (3, 2));
        assert_eq!(m.as_bytes(), &[3, 2, 1, 6, 5, 4]);
    }
}
