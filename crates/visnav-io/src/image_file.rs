//! Image files to and from [`GrayImage`] (the `image` crate decodes and encodes): the file side
//! of visnav-core's pure grayscale image.
//!
//! Colour is converted with the ITU-R BT.601 luma weights (0.299 R + 0.587 G + 0.114 B), as
//! OpenCV's `cvtColor(..., COLOR_RGB2GRAY)` does; 16-bit grey is scaled by 255/65535 to the 8-bit
//! intensity scale SURF's Hessian threshold is defined on.

use std::path::Path;

use crate::vision::{GrayImage, VisionError};

/// [`GrayImage`] from and to files and decoded images. In scope, `GrayImage::load(path)` and
/// `image.save_png(path)` read as methods of the image.
pub trait GrayImageFile: Sized {
    /// Convert any decoded image (gray, RGB, RGBA; for 4-band RGBN GeoTIFFs the 4th band is
    /// ignored). `InvalidImage` when it has no pixels.
    fn from_dynamic(img: &image::DynamicImage) -> Result<Self, VisionError>;
    /// Read an image file (PNG, JPEG, TIFF incl. 4-band GeoTIFF pixels) and convert it to gray.
    fn load(path: &Path) -> Result<Self, VisionError>;
    /// Save as 8-bit PNG (values rounded and clamped to 0..=255, non-finite values as 0).
    fn save_png(&self, path: &Path) -> Result<(), VisionError>;
}

impl GrayImageFile for GrayImage {
    fn from_dynamic(img: &image::DynamicImage) -> Result<Self, VisionError> {
        use image::DynamicImage as D;
        let (w, h) = (img.width() as usize, img.height() as usize);
        let data = match img {
            D::ImageLuma8(g) => g.as_raw().iter().map(|&v| f32::from(v)).collect(),
            D::ImageLuma16(g) => g.as_raw().iter().map(|&v| f32::from(v) / 257.0).collect(),
            other => other
                .to_rgb8()
                .as_raw()
                .chunks_exact(3)
                .map(|p| {
                    0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2])
                })
                .collect(),
        };
        GrayImage::new(w, h, data)
    }

    fn load(path: &Path) -> Result<Self, VisionError> {
        let read_error = |reason: String| VisionError::ImageRead {
            path: path.to_path_buf(),
            reason,
        };
        let img = image::open(path).map_err(|e| read_error(e.to_string()))?;
        if img.width() == 0 || img.height() == 0 {
            return Err(read_error("image has no pixels".into()));
        }
        Self::from_dynamic(&img).map_err(|e| read_error(e.to_string()))
    }

    fn save_png(&self, path: &Path) -> Result<(), VisionError> {
        let buf: Vec<u8> = self
            .data()
            .iter()
            .map(|&v| {
                if v.is_finite() {
                    v.round().clamp(0.0, 255.0) as u8
                } else {
                    0
                }
            })
            .collect();
        image::save_buffer(
            path,
            &buf,
            self.width() as u32,
            self.height() as u32,
            image::ExtendedColorType::L8,
        )
        .map_err(|e| VisionError::ImageWrite {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Grey, 16-bit grey and colour decode to the 8-bit luma scale; a PNG round trip keeps the
    /// rounded values; a missing file names its path.
    #[test]
    fn files_decode_to_luma_and_round_trip() {
        let g8 = image::DynamicImage::ImageLuma8(
            image::GrayImage::from_raw(2, 1, vec![10, 200]).unwrap(),
        );
        let g = GrayImage::from_dynamic(&g8).unwrap();
        assert_eq!(g.data(), &[10.0, 200.0]);
        let g16 = image::DynamicImage::ImageLuma16(
            image::ImageBuffer::from_raw(1, 1, vec![65535u16]).unwrap(),
        );
        assert!((GrayImage::from_dynamic(&g16).unwrap().data()[0] - 255.0).abs() < 1e-3);
        let rgb = image::DynamicImage::ImageRgb8(
            image::RgbImage::from_raw(1, 1, vec![100, 50, 20]).unwrap(),
        );
        let want = 0.299 * 100.0 + 0.587 * 50.0 + 0.114 * 20.0;
        assert!((GrayImage::from_dynamic(&rgb).unwrap().data()[0] - want).abs() < 1e-3);

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("g.png");
        let img = GrayImage::new(3, 2, vec![0.4, 1.6, 254.7, 300.0, -5.0, f32::NAN]).unwrap();
        img.save_png(&path).unwrap();
        let back = GrayImage::load(&path).unwrap();
        assert_eq!(back.data(), &[0.0, 2.0, 255.0, 255.0, 0.0, 0.0]);
        let missing = dir.path().join("none.png");
        let e = GrayImage::load(&missing).unwrap_err().to_string();
        assert!(e.contains("none.png"), "{e}");
    }
}
