//! Grayscale `f32` images for the vision pipeline.
//!
//! Intensities are on the 8-bit scale `0.0..=255.0` (not `0..1`): the SURF Hessian threshold keeps
//! OpenCV's meaning only on that scale. Colour is converted with the ITU-R BT.601 luma weights
//! (0.299 R + 0.587 G + 0.114 B; the application's `vision::file` decodes files), as OpenCV's `cvtColor(..., COLOR_RGB2GRAY)` does, so that timings
//! and repeatability compare with OpenCV on the same input. Pixel `(x, y)` is column `x`, row `y`,
//! with row 0 at the top; pixel centres are at integer coordinates (OpenCV's convention).

use super::VisionError;

/// A row-major grayscale image with `f32` intensities on the 8-bit scale (0..=255).
#[derive(Clone, Debug, PartialEq)]
pub struct GrayImage {
    width: usize,
    height: usize,
    data: Vec<f32>,
}

impl GrayImage {
    /// Wrap row-major pixels. Fails when `data.len() != width * height` or a side is zero.
    pub fn new(width: usize, height: usize, data: Vec<f32>) -> Result<Self, VisionError> {
        if width == 0 || height == 0 {
            return Err(VisionError::InvalidImage(format!(
                "image size {width}x{height}: both sides must be positive"
            )));
        }
        if width.checked_mul(height) != Some(data.len()) {
            return Err(VisionError::InvalidImage(format!(
                "image size {width}x{height} does not match {} pixels",
                data.len()
            )));
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// An image whose pixel `(x, y)` is `f(x, y)`.
    pub fn from_fn(width: usize, height: usize, mut f: impl FnMut(usize, usize) -> f32) -> Self {
        let mut data = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                data.push(f(x, y));
            }
        }
        Self {
            width,
            height,
            data,
        }
    }

    /// Width, pixels.
    pub fn width(&self) -> usize {
        self.width
    }
    /// Height, pixels.
    pub fn height(&self) -> usize {
        self.height
    }
    /// Row-major pixels.
    pub fn data(&self) -> &[f32] {
        &self.data
    }
    /// Row-major pixels, mutable.
    pub fn data_mut(&mut self) -> &mut [f32] {
        &mut self.data
    }
    /// Pixel `(x, y)`; panics when out of bounds (internal use with checked indices).
    #[inline]
    pub fn get(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    /// The `w`x`h` window whose top-left pixel is `(x0, y0)`; `None` when it does not fit.
    pub fn crop(&self, x0: usize, y0: usize, w: usize, h: usize) -> Option<Self> {
        if w == 0 || h == 0 || x0 + w > self.width || y0 + h > self.height {
            return None;
        }
        let mut data = Vec::with_capacity(w * h);
        for y in y0..y0 + h {
            data.extend_from_slice(&self.data[y * self.width + x0..y * self.width + x0 + w]);
        }
        Some(Self {
            width: w,
            height: h,
            data,
        })
    }

    /// Bilinear sample at continuous coordinates (pixel centres at integers); `None` outside.
    #[inline]
    pub fn sample_bilinear(&self, x: f64, y: f64) -> Option<f32> {
        if !(x >= 0.0 && y >= 0.0) {
            return None;
        }
        let x0 = x.floor() as usize;
        let y0 = y.floor() as usize;
        if x0 >= self.width || y0 >= self.height {
            return None;
        }
        let x1 = (x0 + 1).min(self.width - 1);
        let y1 = (y0 + 1).min(self.height - 1);
        if x > (self.width - 1) as f64 || y > (self.height - 1) as f64 {
            return None;
        }
        let fx = (x - x0 as f64) as f32;
        let fy = (y - y0 as f64) as f32;
        let a = self.get(x0, y0) * (1.0 - fx) + self.get(x1, y0) * fx;
        let b = self.get(x0, y1) * (1.0 - fx) + self.get(x1, y1) * fx;
        Some(a * (1.0 - fy) + b * fy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn new_rejects_bad_sizes() {
        assert!(GrayImage::new(0, 3, vec![]).is_err());
        assert!(GrayImage::new(2, 2, vec![0.0; 3]).is_err());
        assert!(GrayImage::new(2, 2, vec![0.0; 4]).is_ok());
    }

    #[test]
    fn crop_and_bilinear() {
        let img = GrayImage::from_fn(5, 4, |x, y| (x + 10 * y) as f32);
        let c = img.crop(1, 1, 3, 2).unwrap();
        assert_eq!(c.data(), &[11.0, 12.0, 13.0, 21.0, 22.0, 23.0]);
        assert!(img.crop(3, 3, 3, 2).is_none());
        let v = img.sample_bilinear(1.5, 2.25).unwrap();
        assert!((v - (1.5 + 22.5)).abs() < 1e-4);
        assert!(img.sample_bilinear(-0.1, 0.0).is_none());
        assert!(img.sample_bilinear(4.0, 3.0).is_some());
        assert!(img.sample_bilinear(4.01, 3.0).is_none());
    }
}
