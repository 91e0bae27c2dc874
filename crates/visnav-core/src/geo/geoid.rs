//! Geoid undulation N (height of the geoid above the WGS84 ellipsoid) and the conversion between
//! heights above mean sea level (orthometric, `alt_amsl_m`, H) and above the ellipsoid
//! (`h_ellip_m`, h): h = H + N.
//!
//! Model: EGM96 (NIMA/NASA 1996, degree and order 360, with the Rapp (1996) height-anomaly to
//! undulation correction, referred to WGS84), sampled on a 15' (0.25 deg) grid bundled in the
//! binary (`data/geoid/egm96_15min_cm.i16le`, 2 MB; source, licence and generator in
//! `data/geoid/README.md`). Values are stored as i16 centimetres (quantisation <= 5 mm).
//!
//! Interpolation: bicubic convolution (R. G. Keys, "Cubic convolution interpolation for digital
//! image processing", IEEE Trans. ASSP 29 (1981), a = -1/2) over the 4 x 4 surrounding nodes;
//! longitude wraps around, and rows beyond a pole are taken from the opposite meridian
//! (lat 90 + d, lon -> lat 90 - d, lon + 180).
//! GeographicLib reports for its own 15' EGM96 grid a maximum cubic interpolation error of about
//! 0.2 m against the full model (bilinear: about 1 m); typical errors are about 1 cm.
//!
//! Accuracy against reality: EGM96 itself is good to about 0.5-1 m in most of the world and worse
//! (a few metres) in the Himalaya, the Andes and parts of Africa. EGM2008 differs from EGM96 by
//! typically a few decimetres (e.g. +0.08 m at Timbuktu, -0.6 m at the south pole). Maps whose
//! heights refer to EGM2008 (such as the NGI data set) are therefore converted with that extra
//! uncertainty.

use super::error::{GeoError, check_finite, check_lat_deg};

/// Name of the geoid model behind [`geoid_undulation_m`].
pub const GEOID_MODEL: &str = "EGM96 (15' grid, bicubic)";

/// Grid spacing, degrees.
const STEP_DEG: f64 = 0.25;
/// Rows from +90 to -90 deg latitude.
const ROWS: usize = 721;
/// Columns from 0 to 359.75 deg longitude.
const COLS: usize = 1440;

static GRID: &[u8] = include_bytes!("../../data/geoid/egm96_15min_cm.i16le");
const _: () = assert!(
    GRID.len() == ROWS * COLS * 2,
    "geoid grid has the wrong size"
);

/// Grid value (metres) at row `r` (0 = +90 deg) and column `c` (0 = 0 deg); `r` may be -1 or
/// ROWS (one row beyond a pole), `c` any integer.
fn node_m(r: i64, c: i64) -> f64 {
    let (r, c) = if r < 0 {
        (-r, c + (COLS as i64) / 2)
    } else if r >= ROWS as i64 {
        (2 * (ROWS as i64 - 1) - r, c + (COLS as i64) / 2)
    } else {
        (r, c)
    };
    let c = c.rem_euclid(COLS as i64) as usize;
    let r = (r.clamp(0, ROWS as i64 - 1)) as usize;
    let i = 2 * (r * COLS + c);
    f64::from(i16::from_le_bytes([GRID[i], GRID[i + 1]])) * 0.01
}

/// Keys cubic convolution weights (a = -1/2) for fractional position t in [0, 1).
fn keys_weights(t: f64) -> [f64; 4] {
    let t2 = t * t;
    let t3 = t2 * t;
    [
        -0.5 * t3 + t2 - 0.5 * t,
        1.5 * t3 - 2.5 * t2 + 1.0,
        -1.5 * t3 + 2.0 * t2 + 0.5 * t,
        0.5 * t3 - 0.5 * t2,
    ]
}

/// Geoid undulation N at a point, metres (EGM96). Errors on a non-finite input or a latitude
/// outside [-90, 90]; any finite longitude is accepted.
pub fn geoid_undulation_m(lat_deg: f64, lon_deg: f64) -> Result<f64, GeoError> {
    check_lat_deg(lat_deg)?;
    check_finite("lon_deg", lon_deg)?;
    let fy = (90.0 - lat_deg) / STEP_DEG; // 0 ..= 720
    let fx = lon_deg.rem_euclid(360.0) / STEP_DEG; // 0 .. 1440
    let r0 = (fy.floor() as i64).min(ROWS as i64 - 2);
    let c0 = fx.floor() as i64;
    let wy = keys_weights(fy - r0 as f64);
    let wx = keys_weights(fx - c0 as f64);
    let mut n = 0.0;
    for (i, wyi) in wy.iter().enumerate() {
        let r = r0 - 1 + i as i64;
        let mut row = 0.0;
        for (j, wxj) in wx.iter().enumerate() {
            row += wxj * node_m(r, c0 - 1 + j as i64);
        }
        n += wyi * row;
    }
    Ok(n)
}

/// Height above the ellipsoid from height above mean sea level: h = H + N.
pub fn h_ellip_from_amsl_m(lat_deg: f64, lon_deg: f64, alt_amsl_m: f64) -> Result<f64, GeoError> {
    check_finite("alt_amsl_m", alt_amsl_m)?;
    Ok(alt_amsl_m + geoid_undulation_m(lat_deg, lon_deg)?)
}

/// Height above mean sea level from height above the ellipsoid: H = h - N.
pub fn amsl_from_h_ellip_m(lat_deg: f64, lon_deg: f64, h_ellip_m: f64) -> Result<f64, GeoError> {
    check_finite("h_ellip_m", h_ellip_m)?;
    Ok(h_ellip_m - geoid_undulation_m(lat_deg, lon_deg)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// NGA's published EGM96 check values: README of the EGM96 15' interpolation program INTPT.F
    /// (sample output OUTINTPT.DAT, https://earth-info.nga.mil/GandG/wgs84/gravitymod/egm96/),
    /// latitude, longitude (0..360 E), N in metres.
    const NGA_EGM96: [(f64, f64, f64); 6] = [
        (38.6281550, 269.7791550, -31.628),
        (-14.6212170, 305.0211140, -2.969),
        (46.8743190, 102.4487290, -43.575),
        (-23.6174460, 133.8747120, 15.871),
        (38.6254730, 359.9995000, 50.066),
        (-0.4667440, 0.0023000, 17.329),
    ];

    #[test]
    fn nga_reference_values() {
        let mut worst_m: f64 = 0.0;
        for (lat, lon, n_ref) in NGA_EGM96 {
            let n = geoid_undulation_m(lat, lon).unwrap();
            worst_m = worst_m.max((n - n_ref).abs());
            assert!(
                (n - n_ref).abs() < 0.05,
                "N({lat}, {lon}) = {n}, NGA {n_ref}"
            );
            // The same point with the longitude given west-negative.
            let n_w = geoid_undulation_m(lat, lon - 360.0).unwrap();
            assert!((n_w - n).abs() < 1e-12);
        }
        eprintln!("worst difference to the NGA EGM96 check values: {worst_m:.4} m");
    }

    /// GeographicLib GeoidEval(1) manual page, EXAMPLES: "The height of the EGM96 geoid at
    /// Timbuktu: echo 16:46:33N 3:00:34W | GeoidEval => 28.7068" (egm96-5 grid). The same
    /// documentation's tables give N(0, 0) = 17.163 m and N(90, *) = 13.605 m, N(-90, *) = -29.535 m
    /// for egm96-5 (as quoted in PyGeodesy's geoids module).
    #[test]
    fn geographiclib_reference_values() {
        let lat = 16.0 + 46.0 / 60.0 + 33.0 / 3600.0;
        let lon = -(3.0 + 0.0 / 60.0 + 34.0 / 3600.0);
        let n = geoid_undulation_m(lat, lon).unwrap();
        eprintln!("Timbuktu: N = {n:.4} m (GeoidEval 28.7068)");
        assert!((n - 28.7068).abs() < 0.05, "Timbuktu N = {n}");
        let n = geoid_undulation_m(0.0, 0.0).unwrap();
        assert!((n - 17.163).abs() < 0.05, "N(0,0) = {n}");
        for lon in [-180.0, -33.0, 0.0, 77.7, 179.99] {
            let n = geoid_undulation_m(90.0, lon).unwrap();
            assert!((n - 13.605).abs() < 0.05, "N(90,{lon}) = {n}");
            let n = geoid_undulation_m(-90.0, lon).unwrap();
            assert!((n + 29.535).abs() < 0.05, "N(-90,{lon}) = {n}");
        }
    }

    #[test]
    fn height_conversions_and_errors() {
        let (lat, lon) = (-33.67, 24.40);
        let n = geoid_undulation_m(lat, lon).unwrap();
        let h = h_ellip_from_amsl_m(lat, lon, 500.0).unwrap();
        assert!((h - (500.0 + n)).abs() < 1e-12);
        assert!((amsl_from_h_ellip_m(lat, lon, h).unwrap() - 500.0).abs() < 1e-9);
        assert!(geoid_undulation_m(90.5, 0.0).is_err());
        assert!(geoid_undulation_m(f64::NAN, 0.0).is_err());
        assert!(geoid_undulation_m(0.0, f64::INFINITY).is_err());
        assert!(h_ellip_from_amsl_m(0.0, 0.0, f64::NAN).is_err());
        assert!(amsl_from_h_ellip_m(0.0, 0.0, f64::NEG_INFINITY).is_err());
    }

    #[test]
    fn reproduces_grid_nodes() {
        // At a node the cubic convolution returns the node value exactly.
        for (r, c) in [
            (0usize, 0usize),
            (100, 37),
            (360, 720),
            (500, 1439),
            (720, 5),
        ] {
            let lat = 90.0 - STEP_DEG * r as f64;
            let lon = STEP_DEG * c as f64;
            let n = geoid_undulation_m(lat, lon).unwrap();
            assert!(
                (n - node_m(r as i64, c as i64)).abs() < 1e-9,
                "node ({r},{c})"
            );
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]

        /// Within the global range of EGM96 (-107 m .. +86 m) and continuous: two points 1 m apart
        /// differ by far less than a centimetre.
        #[test]
        fn bounded_and_continuous(lat in -90.0f64..=90.0, lon in -540.0f64..540.0) {
            let n = geoid_undulation_m(lat, lon).unwrap();
            prop_assert!((-108.0..=87.0).contains(&n), "N = {n}");
            let dlat = if lat > 0.0 { -1e-5 } else { 1e-5 };
            let n2 = geoid_undulation_m(lat + dlat, lon + 1e-5).unwrap();
            prop_assert!((n2 - n).abs() < 0.01, "{n} vs {n2}");
        }

        #[test]
        fn amsl_round_trip(lat in -90.0f64..=90.0, lon in -180.0f64..180.0, h in -500.0f64..10_000.0) {
            let alt = amsl_from_h_ellip_m(lat, lon, h).unwrap();
            let back = h_ellip_from_amsl_m(lat, lon, alt).unwrap();
            prop_assert!((back - h).abs() < 1e-9);
        }
    }
}
