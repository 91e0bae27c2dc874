//! Detector/descriptor evaluation after K. Mikolajczyk & C. Schmid (IJCV 65, 2005, "A comparison
//! of affine region detectors"; PAMI 27(10), 2005, "A performance evaluation of local descriptors"),
//! with ground-truth homographies, plus the synthetic image transformations used to create pairs.
//!
//! * A keypoint is a circular region of radius `3 sigma` (SURF: `sigma = s = 1.2 L / 9`; OpenCV
//!   SIFT: `sigma = size / 2`), the same rule for every detector.
//! * A region of image 1 is mapped into image 2 through the homography `H12` (`p2 ~ H12 p1`, pixel
//!   coordinates with centres at integers): its centre exactly, its radius by `sqrt|det J|` of the
//!   local Jacobian (the circle approximation of the projected ellipse, exact for similarities).
//! * Only regions whose mapped circle lies entirely inside the other image count (common part).
//! * Two regions correspond when their overlap error `1 - area(A and B) / area(A or B)` is below
//!   `max_overlap_error` (0.4 in the papers); correspondences are one-to-one, assigned greedily by
//!   increasing error.
//! * Repeatability = correspondences / min(n1, n2) over the common part.
//! * Matching score = correct nearest-neighbour descriptor matches / min(n1, n2), a match being
//!   correct when its two regions correspond.
//!
//! Pair generation: image 1 is a window of a source image; image 2 of the same size is rendered
//! from the same source through the homography with bilinear interpolation, averaging `k x k`
//! subsamples per pixel when the view shrinks (`k = ceil(1/zoom)`), so no border is ever filled.

use nalgebra::{Matrix3, Vector3};

use visnav_core::vision::{Features, GrayImage, MatchParams, VisionError, match_features};

/// A circular region: centre and radius in pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Region {
    /// Centre column, px.
    pub x: f64,
    /// Centre row, px.
    pub y: f64,
    /// Radius, px.
    pub radius: f64,
}

/// Scores of one image pair.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct PairScore {
    /// Regions of image 1 in the common part.
    pub n1: usize,
    /// Regions of image 2 in the common part.
    pub n2: usize,
    /// One-to-one region correspondences (overlap error below the limit).
    pub correspondences: usize,
    /// `correspondences / min(n1, n2)`.
    pub repeatability: f64,
    /// Nearest-neighbour descriptor matches whose regions correspond.
    pub correct_matches: usize,
    /// `correct_matches / min(n1, n2)`.
    pub matching_score: f64,
}

/// Region of a SURF keypoint (radius `3 s`).
pub fn surf_regions(f: &Features) -> Vec<Region> {
    f.keypoints
        .iter()
        .map(|k| Region {
            x: f64::from(k.x),
            y: f64::from(k.y),
            radius: 3.0 * f64::from(k.scale),
        })
        .collect()
}

/// Map a point through a homography; `None` when it goes to infinity or is not finite.
pub fn project(h: &Matrix3<f64>, x: f64, y: f64) -> Option<(f64, f64)> {
    let p = h * Vector3::new(x, y, 1.0);
    if p.z.abs() < 1e-12 {
        return None;
    }
    let (u, v) = (p.x / p.z, p.y / p.z);
    (u.is_finite() && v.is_finite()).then_some((u, v))
}

/// Map a region: centre through `h`, radius by `sqrt|det J|` of the Jacobian at the centre.
pub fn project_region(h: &Matrix3<f64>, r: &Region) -> Option<Region> {
    let (u, v) = project(h, r.x, r.y)?;
    let e = 1e-3;
    let (ux, vx) = project(h, r.x + e, r.y)?;
    let (uy, vy) = project(h, r.x, r.y + e)?;
    let det = ((ux - u) * (vy - v) - (uy - u) * (vx - v)) / (e * e);
    let radius = r.radius * det.abs().sqrt();
    radius.is_finite().then_some(Region { x: u, y: v, radius })
}

/// Area of the intersection of two circles.
pub fn circle_intersection(a: &Region, b: &Region) -> f64 {
    let d = (a.x - b.x).hypot(a.y - b.y);
    let (r1, r2) = (a.radius, b.radius);
    if d >= r1 + r2 {
        return 0.0;
    }
    if d <= (r1 - r2).abs() {
        let r = r1.min(r2);
        return std::f64::consts::PI * r * r;
    }
    let a1 = ((d * d + r1 * r1 - r2 * r2) / (2.0 * d * r1))
        .clamp(-1.0, 1.0)
        .acos();
    let a2 = ((d * d + r2 * r2 - r1 * r1) / (2.0 * d * r2))
        .clamp(-1.0, 1.0)
        .acos();
    r1 * r1 * (a1 - a1.sin() * a1.cos()) + r2 * r2 * (a2 - a2.sin() * a2.cos())
}

/// Overlap error `1 - |A and B| / |A or B|` of two circles.
pub fn overlap_error(a: &Region, b: &Region) -> f64 {
    let i = circle_intersection(a, b);
    let u = std::f64::consts::PI * (a.radius * a.radius + b.radius * b.radius) - i;
    if u <= 0.0 { 1.0 } else { 1.0 - i / u }
}

fn inside(r: &Region, w: usize, h: usize) -> bool {
    r.x - r.radius >= -0.5
        && r.y - r.radius >= -0.5
        && r.x + r.radius <= w as f64 - 0.5
        && r.y + r.radius <= h as f64 - 0.5
}

/// Indices of the regions kept in image 1 and image 2, and the pairs `(i1, i2, overlap_error)`.
pub type Correspondences = (Vec<usize>, Vec<usize>, Vec<(usize, usize, f64)>);

/// The common-part filter and the greedy one-to-one correspondences. Returns the indices of the
/// regions kept in each image and the corresponding pairs `(i1, i2, overlap_error)`.
pub fn correspondences(
    r1: &[Region],
    r2: &[Region],
    h12: &Matrix3<f64>,
    size1: (usize, usize),
    size2: (usize, usize),
    max_overlap_error: f64,
) -> Result<Correspondences, VisionError> {
    let h21 = h12
        .try_inverse()
        .ok_or_else(|| VisionError::InvalidImage("the homography h12 is singular".into()))?;
    // Regions of image 1 mapped into image 2, kept when inside both images.
    let mut keep1 = Vec::new();
    let mut mapped1 = Vec::new();
    for (i, r) in r1.iter().enumerate() {
        if !inside(r, size1.0, size1.1) {
            continue;
        }
        if let Some(m) = project_region(h12, r)
            && inside(&m, size2.0, size2.1)
        {
            keep1.push(i);
            mapped1.push(m);
        }
    }
    let mut keep2 = Vec::new();
    for (j, r) in r2.iter().enumerate() {
        if !inside(r, size2.0, size2.1) {
            continue;
        }
        if let Some(m) = project_region(&h21, r)
            && inside(&m, size1.0, size1.1)
        {
            keep2.push(j);
        }
    }
    let mut pairs = Vec::new();
    for (a, m) in keep1.iter().zip(&mapped1) {
        for &j in &keep2 {
            let b = &r2[j];
            if (m.x - b.x).abs() > m.radius + b.radius || (m.y - b.y).abs() > m.radius + b.radius {
                continue;
            }
            let e = overlap_error(m, b);
            if e < max_overlap_error {
                pairs.push((*a, j, e));
            }
        }
    }
    pairs.sort_by(|a, b| a.2.total_cmp(&b.2));
    let mut used1 = vec![false; r1.len()];
    let mut used2 = vec![false; r2.len()];
    let mut one_to_one = Vec::new();
    for (i, j, e) in pairs {
        if !used1[i] && !used2[j] {
            used1[i] = true;
            used2[j] = true;
            one_to_one.push((i, j, e));
        }
    }
    Ok((keep1, keep2, one_to_one))
}

/// Repeatability and matching score of two feature sets related by `h12`.
pub fn score_pair(
    f1: &Features,
    f2: &Features,
    h12: &Matrix3<f64>,
    size1: (usize, usize),
    size2: (usize, usize),
) -> Result<PairScore, VisionError> {
    const MAX_ERR: f64 = 0.4;
    let (r1, r2) = (surf_regions(f1), surf_regions(f2));
    let (keep1, keep2, corr) = correspondences(&r1, &r2, h12, size1, size2, MAX_ERR)?;
    let (n1, n2) = (keep1.len(), keep2.len());
    let denom = n1.min(n2).max(1) as f64;
    // Nearest-neighbour matching restricted to the common part (no ratio test).
    let sub = |f: &Features, keep: &[usize]| -> Result<Features, VisionError> {
        let st = f.kind().stride();
        let mut d = Vec::with_capacity(keep.len() * st);
        for &i in keep {
            d.extend_from_slice(&f.descriptors_padded()[i * st..(i + 1) * st]);
        }
        Features::new(keep.iter().map(|&i| f.keypoints[i]).collect(), d, f.kind())
    };
    let (s1, s2) = (sub(f1, &keep1)?, sub(f2, &keep2)?);
    let params = MatchParams {
        ratio: 1.0,
        ..MatchParams::default()
    };
    let matches = match_features(&s1, &s2, &params, None)?;
    let mut ok = std::collections::HashSet::new();
    for &(i, j, _) in &corr {
        ok.insert((i, j));
    }
    // Any corresponding pair counts as correct (not only the greedy one-to-one assignment), but
    // each train region at most once so the score cannot exceed 1.
    let mut trains = std::collections::HashSet::new();
    let correct = matches
        .iter()
        .filter(|m| {
            let (i, j) = (keep1[m.query], keep2[m.train]);
            ok.contains(&(i, j)) || {
                let a = project_region(h12, &r1[i]);
                a.is_some_and(|a| overlap_error(&a, &r2[j]) < MAX_ERR)
            }
        })
        .filter(|m| trains.insert(m.train))
        .count();
    Ok(PairScore {
        n1,
        n2,
        correspondences: corr.len(),
        repeatability: corr.len() as f64 / denom,
        correct_matches: correct,
        matching_score: correct as f64 / denom,
    })
}

/// A synthetic change applied to image 2 of a pair.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub enum Change {
    /// Rotation about the window centre, degrees (positive: clockwise on screen, x towards y).
    Rotation {
        /// The angle, deg.
        deg: f64,
    },
    /// Zoom about the window centre (2.0: everything twice as large in image 2).
    Zoom {
        /// The scale factor.
        factor: f64,
    },
    /// Gaussian blur, sigma in pixels.
    Blur {
        /// The blur's sigma, px.
        sigma: f64,
    },
    /// Additive Gaussian noise, sigma in grey levels (deterministic seed).
    Noise {
        /// The noise's sigma, grey levels.
        sigma: f64,
    },
    /// `v' = gain v + bias`, clamped to 0..=255.
    Photometric {
        /// The gain.
        gain: f64,
        /// The bias, grey levels.
        bias: f64,
    },
}

impl Change {
    /// Short label for tables.
    pub fn label(&self) -> String {
        match self {
            Self::Rotation { deg } => format!("rotation {deg:.0} deg"),
            Self::Zoom { factor } => format!("scale {factor:.2}"),
            Self::Blur { sigma } => format!("blur sigma {sigma:.1}"),
            Self::Noise { sigma } => format!("noise sigma {sigma:.0}"),
            Self::Photometric { gain, bias } => format!("gain {gain:.2} bias {bias:+.0}"),
        }
    }
}

/// An image pair with its ground truth `p2 ~ h12 p1`.
#[derive(Clone, Debug)]
pub struct ImagePair {
    /// The change in words ([`Change::label`]).
    pub label: String,
    /// Image 1: the window of the source.
    pub img1: GrayImage,
    /// Image 2: the window seen through the change.
    pub img2: GrayImage,
    /// Homography from image 1 to image 2 pixels.
    pub h12: Matrix3<f64>,
}

/// Homography of a rotation by `deg` and zoom by `zoom` about `(cx, cy)`.
pub fn similarity_about(cx: f64, cy: f64, deg: f64, zoom: f64) -> Matrix3<f64> {
    let (s, c) = deg.to_radians().sin_cos();
    let t1 = Matrix3::new(1.0, 0.0, cx, 0.0, 1.0, cy, 0.0, 0.0, 1.0);
    let r = Matrix3::new(
        zoom * c,
        -zoom * s,
        0.0,
        zoom * s,
        zoom * c,
        0.0,
        0.0,
        0.0,
        1.0,
    );
    let t0 = Matrix3::new(1.0, 0.0, -cx, 0.0, 1.0, -cy, 0.0, 0.0, 1.0);
    t1 * r * t0
}

/// Render `w x h` pixels of `src` seen through `h_src_to_dst`; `k x k` subsamples per pixel.
/// Fails when a sample falls outside `src`.
pub fn warp(
    src: &GrayImage,
    h_src_to_dst: &Matrix3<f64>,
    w: usize,
    h: usize,
    k: usize,
) -> Result<GrayImage, VisionError> {
    let inv = h_src_to_dst
        .try_inverse()
        .ok_or_else(|| VisionError::InvalidImage("the warp's homography is singular".into()))?;
    let k = k.max(1);
    let mut data = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0f32;
            for sy in 0..k {
                for sx in 0..k {
                    let px = x as f64 - 0.5 + (sx as f64 + 0.5) / k as f64;
                    let py = y as f64 - 0.5 + (sy as f64 + 0.5) / k as f64;
                    let v = project(&inv, px, py)
                        .and_then(|(u, v)| src.sample_bilinear(u, v))
                        .ok_or_else(|| {
                            VisionError::InvalidImage(format!(
                                "warp: pixel ({x}, {y}) maps outside the {}x{} source",
                                src.width(),
                                src.height()
                            ))
                        })?;
                    acc += v;
                }
            }
            data.push(acc / (k * k) as f32);
        }
    }
    GrayImage::new(w, h, data)
}

/// Separable Gaussian blur (kernel radius `ceil(3 sigma)`, replicated borders).
pub fn gaussian_blur(img: &GrayImage, sigma: f64) -> GrayImage {
    if sigma <= 0.0 {
        return img.clone();
    }
    let r = (3.0 * sigma).ceil() as isize;
    let mut k: Vec<f32> = (-r..=r)
        .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    let s: f32 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= s);
    let (w, h) = (img.width() as isize, img.height() as isize);
    let pass = |src: &GrayImage, horizontal: bool| {
        GrayImage::from_fn(w as usize, h as usize, |x, y| {
            let mut acc = 0.0;
            for (i, kv) in (-r..=r).zip(&k) {
                let (xx, yy) = if horizontal {
                    ((x as isize + i).clamp(0, w - 1), y as isize)
                } else {
                    (x as isize, (y as isize + i).clamp(0, h - 1))
                };
                acc += kv * src.get(xx as usize, yy as usize);
            }
            acc
        })
    };
    pass(&pass(img, true), false)
}

/// Deterministic additive Gaussian noise (xorshift64* + Box-Muller), clamped to 0..=255.
pub fn add_noise(img: &GrayImage, sigma: f64, seed: u64) -> GrayImage {
    let mut s = seed | 1;
    let mut uniform = move || {
        s ^= s >> 12;
        s ^= s << 25;
        s ^= s >> 27;
        ((s.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    let mut out = img.clone();
    for v in out.data_mut() {
        let (u1, u2) = (uniform(), uniform());
        let n = (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
        *v = (f64::from(*v) + sigma * n).clamp(0.0, 255.0) as f32;
    }
    out
}

/// Build a pair from a window `(x0, y0, w, h)` of `src` and a change of image 2.
pub fn make_pair(
    src: &GrayImage,
    window: (usize, usize, usize, usize),
    change: Change,
) -> Result<ImagePair, VisionError> {
    let (x0, y0, w, h) = window;
    let img1 = src.crop(x0, y0, w, h).ok_or_else(|| {
        VisionError::InvalidImage(format!(
            "window x {x0}, y {y0}, {w} x {h} px outside the source"
        ))
    })?;
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let t_src_to_1 = Matrix3::new(
        1.0,
        0.0,
        -(x0 as f64),
        0.0,
        1.0,
        -(y0 as f64),
        0.0,
        0.0,
        1.0,
    );
    let (h12, img2) = match change {
        Change::Rotation { deg } => {
            let h12 = similarity_about(cx, cy, deg, 1.0);
            (h12, warp(src, &(h12 * t_src_to_1), w, h, 1)?)
        }
        Change::Zoom { factor } => {
            let h12 = similarity_about(cx, cy, 0.0, factor);
            let k = (1.0 / factor).ceil().max(1.0) as usize;
            (h12, warp(src, &(h12 * t_src_to_1), w, h, k)?)
        }
        Change::Blur { sigma } => (Matrix3::identity(), gaussian_blur(&img1, sigma)),
        Change::Noise { sigma } => (Matrix3::identity(), add_noise(&img1, sigma, 0x5eed_1234)),
        Change::Photometric { gain, bias } => {
            let mut img2 = img1.clone();
            for v in img2.data_mut() {
                *v = (gain * f64::from(*v) + bias).clamp(0.0, 255.0) as f32;
            }
            (Matrix3::identity(), img2)
        }
    };
    Ok(ImagePair {
        label: change.label(),
        img1,
        img2,
        h12,
    })
}

/// The standard set of changes of the quality table (docs/surf.md).
pub fn standard_changes() -> Vec<Change> {
    let mut v = Vec::new();
    for deg in [0.0, 15.0, 30.0, 45.0, 90.0, 135.0, 180.0] {
        v.push(Change::Rotation { deg });
    }
    for factor in [0.5, 0.7, 1.4, 2.0] {
        v.push(Change::Zoom { factor });
    }
    for sigma in [1.0, 2.0, 3.0] {
        v.push(Change::Blur { sigma });
    }
    for sigma in [5.0, 10.0, 20.0] {
        v.push(Change::Noise { sigma });
    }
    v.push(Change::Photometric {
        gain: 0.6,
        bias: 0.0,
    });
    v.push(Change::Photometric {
        gain: 1.3,
        bias: -20.0,
    });
    v.push(Change::Photometric {
        gain: 1.0,
        bias: 40.0,
    });
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overlap_error_of_circles() {
        let a = Region {
            x: 0.0,
            y: 0.0,
            radius: 2.0,
        };
        assert!(overlap_error(&a, &a).abs() < 1e-12);
        let far = Region { x: 10.0, ..a };
        assert_eq!(overlap_error(&a, &far), 1.0);
        // Concentric radii 1 and 2: error 1 - 1/4.
        let small = Region { radius: 1.0, ..a };
        assert!((overlap_error(&a, &small) - 0.75).abs() < 1e-12);
        // Symmetric, and partial overlap monotone in distance.
        let b = Region { x: 1.0, ..a };
        let c = Region { x: 2.0, ..a };
        assert!((overlap_error(&a, &b) - overlap_error(&b, &a)).abs() < 1e-12);
        assert!(overlap_error(&a, &b) < overlap_error(&a, &c));
        // Lens area for two unit circles at distance 1: 2 pi/3 - sqrt(3)/2.
        let u = Region {
            x: 0.0,
            y: 0.0,
            radius: 1.0,
        };
        let v = Region {
            x: 1.0,
            y: 0.0,
            radius: 1.0,
        };
        let want = 2.0 * std::f64::consts::PI / 3.0 - 3f64.sqrt() / 2.0;
        assert!((circle_intersection(&u, &v) - want).abs() < 1e-9);
    }

    #[test]
    fn similarity_maps_centre_to_itself_and_scales_radii() {
        let h = similarity_about(50.0, 40.0, 30.0, 2.0);
        let (x, y) = project(&h, 50.0, 40.0).unwrap();
        assert!((x - 50.0).abs() < 1e-9 && (y - 40.0).abs() < 1e-9);
        let r = project_region(
            &h,
            &Region {
                x: 60.0,
                y: 40.0,
                radius: 3.0,
            },
        )
        .unwrap();
        assert!((r.radius - 6.0).abs() < 1e-6);
        // +30 deg moves +x towards +y.
        assert!(r.y > 40.0);
    }

    #[test]
    fn warp_rotation_matches_direct_sampling() {
        let src = GrayImage::from_fn(80, 80, |x, y| ((x * 7 + y * 3) % 50) as f32);
        let pair = make_pair(&src, (20, 20, 40, 40), Change::Rotation { deg: 90.0 }).unwrap();
        // Pixel (x, y) of image 1 appears at H12 (x, y) in image 2.
        for (x, y) in [(10usize, 12usize), (25, 30), (19, 19)] {
            let (u, v) = project(&pair.h12, x as f64, y as f64).unwrap();
            let got = pair.img2.get(u.round() as usize, v.round() as usize);
            assert!((got - pair.img1.get(x, y)).abs() < 1e-3, "{x},{y}");
        }
        assert!(make_pair(&src, (0, 0, 80, 80), Change::Rotation { deg: 45.0 }).is_err());
    }

    #[test]
    fn blur_preserves_mean_and_noise_is_deterministic() {
        let img = GrayImage::from_fn(30, 20, |x, y| ((x * y) % 17) as f32 * 10.0);
        let b = gaussian_blur(&img, 2.0);
        let mean = |g: &GrayImage| g.data().iter().sum::<f32>() / g.data().len() as f32;
        assert!((mean(&b) - mean(&img)).abs() < 3.0);
        assert_eq!(add_noise(&img, 10.0, 7), add_noise(&img, 10.0, 7));
        assert_ne!(add_noise(&img, 10.0, 7), img);
    }
}
