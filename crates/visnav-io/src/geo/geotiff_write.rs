//! GeoTIFF writer: one [`Raster`] as a deflate-compressed, stripped GeoTIFF that
//! [`super::geotiff::load_geotiff`] (and GDAL) read back with the same samples, transform, CRS
//! and nodata.
//!
//! What it writes: 8-bit samples (1 band grey, 3 bands RGB, chunky) or 32-bit float samples (1
//! band: a DEM); ModelPixelScale + ModelTiepoint for a north-up transform, ModelTransformation for
//! any other; GTModelTypeGeoKey (projected or geographic), GTRasterTypeGeoKey = PixelIsArea, and
//! ProjectedCSTypeGeoKey / GeographicTypeGeoKey with the CRS's EPSG code (UTM on WGS84 326zz /
//! 327zz, web Mercator 3857, WGS84 4326); GDAL_NODATA (42113) when the raster has a nodata value.
//! A generic transverse Mercator has no EPSG code: it is refused (name one with
//! `crs_override` when reading instead).
//!
//! Used where visnav makes an image of its own for the map build to read (the simulator's
//! degraded map copies); a user's orthophotos are read, never rewritten.

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use tiff::encoder::colortype::{Gray8, Gray32Float, RGB8};
use tiff::encoder::compression::DeflateLevel;
use tiff::encoder::{Compression, TiffEncoder};
use tiff::tags::Tag;

use visnav_core::geo::Crs;
use visnav_core::geo::raster::{Raster, RasterData};

/// Why a raster could not be written.
#[derive(Debug, thiserror::Error)]
pub enum GeoTiffWriteError {
    /// The raster cannot be written in the supported form.
    #[error("{path}: {reason}")]
    Unsupported {
        /// The file.
        path: String,
        /// What is wrong, in words.
        reason: String,
    },
    /// Writing the file failed.
    #[error("{path}: {reason}")]
    Io {
        /// The file.
        path: String,
        /// What is wrong, in words.
        reason: String,
    },
}

/// GeoKey ids written.
const GT_MODEL_TYPE: u16 = 1024;
const GT_RASTER_TYPE: u16 = 1025;
const GEOGRAPHIC_TYPE: u16 = 2048;
const PROJECTED_CS_TYPE: u16 = 3072;
/// GTModelType values.
const MODEL_PROJECTED: u16 = 1;
const MODEL_GEOGRAPHIC: u16 = 2;
/// GTRasterType: RasterPixelIsArea (the transform maps pixel corners).
const RASTER_PIXEL_IS_AREA: u16 = 1;
/// The GDAL_NODATA tag (ASCII).
const TAG_GDAL_NODATA: u16 = 42113;

/// Writes `raster` to `path` (see the module doc for what is written and refused).
pub fn write_geotiff(raster: &Raster, path: &Path) -> Result<(), GeoTiffWriteError> {
    let name = path.display().to_string();
    let unsupported = |reason: String| GeoTiffWriteError::Unsupported {
        path: name.clone(),
        reason,
    };
    let keys = geo_keys(raster.crs()).ok_or_else(|| {
        unsupported(format!(
            "the CRS {} has no EPSG code to write",
            raster.crs()
        ))
    })?;
    let io = |e: &dyn std::fmt::Display| GeoTiffWriteError::Io {
        path: name.clone(),
        reason: e.to_string(),
    };
    let (w, h) = (raster.width(), raster.height());
    let (w32, h32) = match (u32::try_from(w), u32::try_from(h)) {
        (Ok(a), Ok(b)) => (a, b),
        _ => return Err(unsupported(format!("{w} x {h} pixels are too many"))),
    };
    let file = File::create(path).map_err(|e| io(&e))?;
    let mut enc = TiffEncoder::new(BufWriter::new(file))
        .map_err(|e| io(&e))?
        .with_compression(Compression::Deflate(DeflateLevel::Fast));
    let c = raster.transform().coeffs();
    let north_up = c[2] == 0.0 && c[4] == 0.0 && c[1] > 0.0 && c[5] < 0.0;
    let georef =
        |img: &mut tiff::encoder::DirectoryEncoder<'_, _, _>| -> Result<(), tiff::TiffError> {
            if north_up {
                img.write_tag(Tag::ModelPixelScaleTag, &[c[1], -c[5], 0.0][..])?;
                img.write_tag(Tag::ModelTiepointTag, &[0.0, 0.0, 0.0, c[0], c[3], 0.0][..])?;
            } else {
                let m = [
                    c[1], c[2], 0.0, c[0], c[4], c[5], 0.0, c[3], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                    0.0, 1.0,
                ];
                img.write_tag(Tag::ModelTransformationTag, &m[..])?;
            }
            img.write_tag(Tag::GeoKeyDirectoryTag, &keys[..])?;
            if let Some(v) = raster.nodata() {
                img.write_tag(Tag::Unknown(TAG_GDAL_NODATA), format!("{v}").as_str())?;
            }
            Ok(())
        };
    let written = match (raster.data(), raster.bands()) {
        (RasterData::U8(d), 1) => enc.new_image::<Gray8>(w32, h32).and_then(|mut img| {
            georef(img.encoder())?;
            img.write_data(d)
        }),
        (RasterData::U8(d), 3) => enc.new_image::<RGB8>(w32, h32).and_then(|mut img| {
            georef(img.encoder())?;
            img.write_data(d)
        }),
        (RasterData::F32(d), 1) => enc.new_image::<Gray32Float>(w32, h32).and_then(|mut img| {
            georef(img.encoder())?;
            img.write_data(d)
        }),
        (_, bands) => {
            return Err(unsupported(format!(
                "{bands} band(s) of {} samples: only 8-bit grey or RGB and 32-bit float grey are written",
                raster.source_type()
            )));
        }
    };
    written.map_err(|e| io(&e))
}

/// The GeoKeyDirectory of `crs`: header, then (id, location 0, count 1, value) entries sorted by
/// id. None for a CRS without an EPSG code.
fn geo_keys(crs: Crs) -> Option<Vec<u16>> {
    let code = u16::try_from(crs.epsg()?).ok()?;
    let (model, key) = match crs {
        Crs::Geographic => (MODEL_GEOGRAPHIC, GEOGRAPHIC_TYPE),
        _ => (MODEL_PROJECTED, PROJECTED_CS_TYPE),
    };
    let entries = [
        (GT_MODEL_TYPE, model),
        (GT_RASTER_TYPE, RASTER_PIXEL_IS_AREA),
        (key, code),
    ];
    let mut d = vec![1, 1, 0, entries.len() as u16];
    for (id, value) in entries {
        d.extend_from_slice(&[id, 0, 1, value]);
    }
    Some(d)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::geotiff::load_geotiff;
    use visnav_core::geo::raster::GeoTransform;

    fn round_trip(raster: &Raster) -> Raster {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("r.tif");
        write_geotiff(raster, &p).unwrap();
        load_geotiff(&p, None).unwrap()
    }

    #[test]
    fn rgb_grey_and_float_rasters_read_back_the_same() {
        let t = GeoTransform::north_up(493_962.0, 4_878_794.0, 0.3, 0.3).unwrap();
        let utm = Crs::Utm {
            zone: 10,
            north: true,
        };
        let rgb: Vec<u8> = (0..5 * 4 * 3).map(|i| (i * 7 % 251) as u8).collect();
        let r = Raster::new(5, 4, 3, RasterData::U8(rgb), t, utm, Some(0.0)).unwrap();
        let back = round_trip(&r);
        assert_eq!(back.data(), r.data());
        assert_eq!(back.transform().coeffs(), r.transform().coeffs());
        assert_eq!(back.crs(), utm);
        assert_eq!(back.nodata(), Some(0.0));

        let grey: Vec<u8> = (0..6 * 3).map(|i| i as u8).collect();
        let r = Raster::new(6, 3, 1, RasterData::U8(grey), t, Crs::WebMercator, None).unwrap();
        let back = round_trip(&r);
        assert_eq!(back.data(), r.data());
        assert_eq!(back.crs(), Crs::WebMercator);
        assert_eq!(back.nodata(), None);

        let dem: Vec<f32> = (0..4 * 4).map(|i| 120.5 + i as f32).collect();
        let south = Crs::Utm {
            zone: 34,
            north: false,
        };
        let r = Raster::new(4, 4, 1, RasterData::F32(dem), t, south, Some(-9999.0)).unwrap();
        let back = round_trip(&r);
        assert_eq!(back.data(), r.data());
        assert_eq!(back.crs(), south);
        assert_eq!(back.nodata(), Some(-9999.0));
    }

    #[test]
    fn a_rotated_transform_and_geographic_coordinates_read_back() {
        let t = GeoTransform::new([24.0, 0.001, 0.0002, -33.0, 0.0001, -0.001]).unwrap();
        let r = Raster::new(
            3,
            2,
            1,
            RasterData::U8(vec![1, 2, 3, 4, 5, 6]),
            t,
            Crs::Geographic,
            None,
        )
        .unwrap();
        let back = round_trip(&r);
        assert_eq!(back.crs(), Crs::Geographic);
        for (a, b) in back.transform().coeffs().iter().zip(r.transform().coeffs()) {
            assert!((a - b).abs() < 1e-12, "{a} {b}");
        }
    }

    #[test]
    fn what_cannot_be_written_is_refused_with_the_file_named() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("tm.tif");
        let t = GeoTransform::north_up(0.0, 0.0, 1.0, 1.0).unwrap();
        let tm = Crs::TransverseMercator {
            lat0_deg: 0.0,
            lon0_deg: 25.0,
            k0: 1.0,
            false_easting_m: 0.0,
            false_northing_m: 0.0,
        };
        let r = Raster::new(2, 2, 1, RasterData::U8(vec![0; 4]), t, tm, None).unwrap();
        let e = write_geotiff(&r, &p).unwrap_err().to_string();
        assert!(e.contains("tm.tif") && e.contains("EPSG"), "{e}");
        let r = Raster::new(
            2,
            2,
            2,
            RasterData::U8(vec![0; 8]),
            t,
            Crs::Geographic,
            None,
        )
        .unwrap();
        let e = write_geotiff(&r, &p).unwrap_err().to_string();
        assert!(e.contains("2 band"), "{e}");
    }
}
