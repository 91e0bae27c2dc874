//! Summed-area table (integral image, Viola & Jones 2001; Bay et al. 2008 sec. 3.1).
//!
//! `I(x, y) = sum of img[v][u] for u < x, v < y`, stored as a `(h+1) x (w+1)` row-major table whose
//! first row and column are zero, so a box sum needs four reads and no branch.
//!
//! Precision vs. speed: intensities are quantised to integers 0..=255 (what an 8-bit camera delivers;
//! OpenCV's SURF requires 8-bit input too) and the table is `i32` with wrapping arithmetic. A box sum
//! computed with wrapping subtraction is exact modulo 2^32, hence exact whenever the true box sum is
//! below 2^31, i.e. for any box of up to 8.4 million pixels, whatever the image size. This keeps
//! 4-byte cells (twice the SIMD width of `f64`) with no rounding error at all, whereas `f32` loses
//! integer precision beyond 2^24 (a 256x256 white area) and `f64` doubles memory traffic.

use super::GrayImage;

/// Integral image with wrapping `i32` cells (see the module documentation for the precision argument).
#[derive(Clone, Debug)]
pub struct IntegralImage {
    width: usize,
    height: usize,
    stride: usize,
    data: Vec<i32>,
}

impl IntegralImage {
    /// Build from a gray image (values rounded and clamped to 0..=255; NaN counts as 0).
    pub fn new(img: &GrayImage) -> Self {
        let (w, h) = (img.width(), img.height());
        let stride = w + 1;
        let mut data = vec![0i32; stride * (h + 1)];
        let mut row = vec![0i32; w];
        for y in 0..h {
            let src = &img.data()[y * w..(y + 1) * w];
            let mut acc = 0i32;
            for (r, &v) in row.iter_mut().zip(src) {
                // `as` saturates and maps NaN to 0.
                let q = (v + 0.5).clamp(0.0, 255.0) as i32;
                acc = acc.wrapping_add(q);
                *r = acc;
            }
            let (prev, cur) = data.split_at_mut((y + 1) * stride);
            let prev = &prev[y * stride + 1..y * stride + 1 + w];
            let cur = &mut cur[1..1 + w];
            for ((c, &p), &r) in cur.iter_mut().zip(prev).zip(&row) {
                *c = p.wrapping_add(r);
            }
        }
        Self {
            width: w,
            height: h,
            stride,
            data,
        }
    }

    /// Width of the source image in pixels.
    pub fn width(&self) -> usize {
        self.width
    }
    /// Height of the source image in pixels.
    pub fn height(&self) -> usize {
        self.height
    }
    /// Cells per table row (`width + 1`).
    pub fn stride(&self) -> usize {
        self.stride
    }
    /// The table, `(height + 1) * stride` cells.
    pub fn data(&self) -> &[i32] {
        &self.data
    }

    /// Table row `y` (`0..=height`), `width + 1` cells.
    #[inline]
    pub fn row(&self, y: usize) -> &[i32] {
        &self.data[y * self.stride..(y + 1) * self.stride]
    }

    /// Sum of the pixels in columns `x0..x1`, rows `y0..y1` (half-open). Requires
    /// `x0 <= x1 <= width`, `y0 <= y1 <= height`.
    #[inline]
    pub fn box_sum(&self, x0: usize, y0: usize, x1: usize, y1: usize) -> i32 {
        let s = self.stride;
        let d = &self.data;
        d[y1 * s + x1]
            .wrapping_sub(d[y0 * s + x1])
            .wrapping_sub(d[y1 * s + x0])
            .wrapping_add(d[y0 * s + x0])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn box_sum_matches_brute_force(w in 1usize..20, h in 1usize..20, seed in 0u64..1000,
                                       a in 0usize..20, b in 0usize..20, c in 0usize..20, d in 0usize..20) {
            let mut s = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
            let img = GrayImage::from_fn(w, h, |_, _| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((s >> 33) % 256) as f32
            });
            let ii = IntegralImage::new(&img);
            let (x0, x1) = (a.min(c).min(w), a.max(c).min(w));
            let (y0, y1) = (b.min(d).min(h), b.max(d).min(h));
            let mut want = 0i64;
            for y in y0..y1 { for x in x0..x1 { want += img.get(x, y) as i64; } }
            prop_assert_eq!(ii.box_sum(x0, y0, x1, y1) as i64, want);
        }
    }

    #[test]
    fn wrapping_keeps_box_sums_exact_on_large_images() {
        // 9000 x 1000 white pixels: the table overflows i32 (2.3e9 > 2^31), box sums stay exact.
        let img = GrayImage::from_fn(9000, 1000, |_, _| 255.0);
        let ii = IntegralImage::new(&img);
        assert_eq!(ii.box_sum(8990, 990, 9000, 1000), 100 * 255);
        assert_eq!(
            ii.box_sum(4000, 0, 8000, 1000) as i64 & 0xffff_ffff,
            (4000i64 * 1000 * 255) & 0xffff_ffff
        );
        assert_eq!(ii.box_sum(0, 0, 3, 3), 9 * 255);
    }

    #[test]
    fn quantises_and_tolerates_nan() {
        let img = GrayImage::new(2, 1, vec![f32::NAN, 300.0]).unwrap();
        let ii = IntegralImage::new(&img);
        assert_eq!(ii.box_sum(0, 0, 2, 1), 255);
    }
}
