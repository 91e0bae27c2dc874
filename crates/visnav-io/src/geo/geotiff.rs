//! GeoTIFF reader: the first image of a file as one [`Raster`] (through the windowed reader's
//! chunk decoding, `super::window`). The format, the georeferencing keys and the errors are
//! `super::geotiff_info`'s, re-exported here.

use std::io::{BufReader, Read, Seek};
use std::path::Path;

pub use super::geotiff_info::*;
use super::window::GeoTiffWindowReader;
use visnav_core::geo::Crs;
use visnav_core::geo::raster::Raster;

/// Loads a GeoTIFF (first image) as a [`Raster`]. `crs_override` is used when the file's CRS keys
/// are missing or not understood; see the module doc. For large files read windows instead
/// ([`super::window::open_geotiff_window`]).
pub fn load_geotiff(path: &Path, crs_override: Option<Crs>) -> Result<Raster, GeoTiffError> {
    let file =
        crate::files::open_regular(path, "a GeoTIFF").map_err(|source| GeoTiffError::Io {
            path: path.to_path_buf(),
            cause: source,
        })?;
    read_geotiff(BufReader::new(file), path, crs_override)
}

/// Like [`load_geotiff`] but from any seekable reader; `path` is only used in error messages.
pub fn read_geotiff<R: Read + Seek + Send>(
    reader: R,
    path: &Path,
    crs_override: Option<Crs>,
) -> Result<Raster, GeoTiffError> {
    guarded(path, || {
        let mut r = GeoTiffWindowReader::new_unguarded(reader, path, crs_override)?;
        // Every chunk is decoded exactly once: no cache.
        r.set_cache_bytes(0);
        let info = r.info().clone();
        let bytes = info
            .width
            .checked_mul(info.height)
            .and_then(|n| n.checked_mul(info.bands))
            .map(|n| n.saturating_mul(usize::from(info.bits_per_sample).div_ceil(8)));
        if bytes.is_none_or(|b| b > MAX_DECODED_BYTES) {
            return Err(GeoTiffError::Decode {
                path: path.to_path_buf(),
                reason: format!(
                    "{} x {} x {} samples of {} bits exceed the {MAX_DECODED_BYTES} byte limit",
                    info.width, info.height, info.bands, info.bits_per_sample
                ),
            });
        }
        let raster = r.read_window_unguarded(0, 0, info.width, info.height)?;
        tracing::debug!(
            file = %path.display(),
            width = info.width, height = info.height, bands = info.bands,
            source_type = ?raster.source_type(), crs = ?info.crs,
            transform = ?info.transform.coeffs(), nodata = ?info.nodata,
            "GeoTIFF loaded"
        );
        Ok(raster)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use tiff::encoder::colortype::{self, ColorType};
    use tiff::encoder::compression::DeflateLevel;
    use tiff::encoder::{Compression, TiffEncoder, TiffValue};
    use tiff::tags::Tag;
    use visnav_core::geo::raster::{RasterData, SampleType};

    /// A tag to write into a synthetic file.
    enum TagVal {
        F64(Vec<f64>),
        U16(Vec<u16>),
        Ascii(&'static str),
    }

    fn write_tiff<C: ColorType>(
        path: &Path,
        w: u32,
        h: u32,
        data: &[C::Inner],
        tags: &[(Tag, TagVal)],
        compression: Compression,
    ) where
        [C::Inner]: TiffValue,
    {
        let file = std::fs::File::create(path).unwrap();
        let mut enc = TiffEncoder::new(file)
            .unwrap()
            .with_compression(compression);
        let mut img = enc.new_image::<C>(w, h).unwrap();
        for (tag, v) in tags {
            match v {
                TagVal::F64(v) => img.encoder().write_tag(*tag, &v[..]).unwrap(),
                TagVal::U16(v) => img.encoder().write_tag(*tag, &v[..]).unwrap(),
                TagVal::Ascii(s) => img.encoder().write_tag(*tag, *s).unwrap(),
            }
        }
        img.write_data(data).unwrap();
    }

    /// One GeoKey directory entry: (id, location, count, value).
    type Key = (u16, u16, u16, u16);

    /// GeoKeyDirectory from (id, location, count, value) entries.
    fn dir(entries: &[(u16, u16, u16, u16)]) -> Vec<u16> {
        let mut d = vec![1, 1, 0, entries.len() as u16];
        for &(a, b, c, e) in entries {
            d.extend_from_slice(&[a, b, c, e]);
        }
        d
    }

    fn utm_tags(pcs: u16, raster_type: u16) -> Vec<(Tag, TagVal)> {
        vec![
            (Tag::ModelPixelScaleTag, TagVal::F64(vec![2.0, 3.0, 0.0])),
            (
                Tag::ModelTiepointTag,
                TagVal::F64(vec![0.0, 0.0, 0.0, 500_000.0, 4_000_000.0, 0.0]),
            ),
            (
                Tag::GeoKeyDirectoryTag,
                TagVal::U16(dir(&[
                    (1024, 0, 1, 1),
                    (1025, 0, 1, raster_type),
                    (3072, 0, 1, pcs),
                    (3076, 0, 1, 9001),
                ])),
            ),
        ]
    }

    const TM_DOUBLES: [f64; 5] = [0.0, 25.0, 1.0, 0.0, 0.0];

    /// The NGI files' user-defined transverse Mercator keys (lat0 0, lon0 25, k 1, FE/FN 0).
    fn tm_keys(extra: &[(u16, u16, u16, u16)]) -> Vec<(u16, u16, u16, u16)> {
        let mut k = vec![
            (1024, 0, 1, 1),
            (1025, 0, 1, 1),
            (2048, 0, 1, 4326),
            (2054, 0, 1, 9102),
            (3072, 0, 1, 32767),
            (3074, 0, 1, 32767),
            (3075, 0, 1, 1),
            (3076, 0, 1, 9001),
            (3080, 34736, 1, 1),
            (3081, 34736, 1, 0),
            (3082, 34736, 1, 3),
            (3083, 34736, 1, 4),
            (3092, 34736, 1, 2),
        ];
        for e in extra {
            k.retain(|x| x.0 != e.0);
            k.push(*e);
        }
        k.sort();
        k
    }

    fn crs_of(entries: &[(u16, u16, u16, u16)], doubles: &[f64]) -> Result<Crs, KeyError> {
        GeoKeys::parse(&dir(entries), Some(doubles), Some("WGS 84|"))
            .unwrap()
            .crs()
    }

    #[test]
    fn epsg_codes_map_to_crs() {
        let one = |pcs: u16| crs_of(&[(1024, 0, 1, 1), (3072, 0, 1, pcs)], &[]);
        assert_eq!(
            one(32610),
            Ok(Crs::Utm {
                zone: 10,
                north: true
            })
        );
        assert_eq!(
            one(32760),
            Ok(Crs::Utm {
                zone: 60,
                north: false
            })
        );
        assert_eq!(
            one(26914),
            Ok(Crs::Utm {
                zone: 14,
                north: true
            })
        );
        assert_eq!(one(3857), Ok(Crs::WebMercator));
        let e = one(2994).unwrap_err();
        assert!(
            e.key.contains("ProjectedCSTypeGeoKey (3072)") && e.reason.contains("2994"),
            "{e:?}"
        );
        assert_eq!(
            crs_of(&[(1024, 0, 1, 2), (2048, 0, 1, 4326)], &[]),
            Ok(Crs::Geographic)
        );
        let e = crs_of(&[(1024, 0, 1, 2), (2048, 0, 1, 4269)], &[]).unwrap_err();
        assert!(e.key.contains("GeographicTypeGeoKey"), "{e:?}");
        // Feet on an EPSG-coded UTM is contradictory.
        let e = crs_of(
            &[(1024, 0, 1, 1), (3072, 0, 1, 32610), (3076, 0, 1, 9002)],
            &[],
        )
        .unwrap_err();
        assert!(e.key.contains("ProjLinearUnitsGeoKey (3076)"), "{e:?}");
        // Model type inferred when missing; geocentric rejected.
        assert_eq!(
            crs_of(&[(3072, 0, 1, 32614)], &[]),
            Ok(Crs::Utm {
                zone: 14,
                north: true
            })
        );
        assert!(crs_of(&[(1024, 0, 1, 3)], &[]).is_err());
        assert!(
            crs_of(&[(1025, 0, 1, 1)], &[])
                .unwrap_err()
                .key
                .contains("GTModelTypeGeoKey")
        );
        // User-defined PCS with a UTM projection code.
        assert_eq!(
            crs_of(
                &[
                    (1024, 0, 1, 1),
                    (2048, 0, 1, 4326),
                    (3072, 0, 1, 32767),
                    (3074, 0, 1, 16135),
                    (3076, 0, 1, 9001)
                ],
                &[]
            ),
            Ok(Crs::Utm {
                zone: 35,
                north: false
            })
        );
    }

    #[test]
    fn user_defined_transverse_mercator() {
        let expect = Crs::TransverseMercator {
            lat0_deg: 0.0,
            lon0_deg: 25.0,
            k0: 1.0,
            false_easting_m: 0.0,
            false_northing_m: 0.0,
        };
        assert_eq!(crs_of(&tm_keys(&[]), &TM_DOUBLES), Ok(expect));
        // Explicit WGS84 ellipsoid parameters (as in the NGI orthos) are fine.
        let d = [0.0, 25.0, 1.0, 0.0, 0.0, 298.257223563, 6378137.0];
        let k = tm_keys(&[(2057, 34736, 1, 6), (2059, 34736, 1, 5)]);
        assert_eq!(crs_of(&k, &d), Ok(expect));
        // Other parameters.
        let d = [-30.0, 31.0, 0.9996, 500_000.0, 10_000_000.0];
        assert_eq!(
            crs_of(&tm_keys(&[]), &d),
            Ok(Crs::TransverseMercator {
                lat0_deg: -30.0,
                lon0_deg: 31.0,
                k0: 0.9996,
                false_easting_m: 500_000.0,
                false_northing_m: 10_000_000.0,
            })
        );
        // Each failure names its key.
        let cases: Vec<(Vec<Key>, Vec<f64>, &str)> = vec![
            (
                tm_keys(&[(3076, 0, 1, 9002)]),
                TM_DOUBLES.to_vec(),
                "ProjLinearUnitsGeoKey",
            ),
            (
                tm_keys(&[(2054, 0, 1, 9101)]),
                TM_DOUBLES.to_vec(),
                "GeogAngularUnitsGeoKey",
            ),
            (
                tm_keys(&[(2048, 0, 1, 4148)]),
                TM_DOUBLES.to_vec(),
                "GeographicTypeGeoKey",
            ),
            (
                tm_keys(&[(2048, 0, 1, 32767), (2050, 0, 1, 6269)]),
                TM_DOUBLES.to_vec(),
                "GeogGeodeticDatumGeoKey",
            ),
            (
                tm_keys(&[(2048, 0, 1, 32767), (2056, 0, 1, 7019)]),
                TM_DOUBLES.to_vec(),
                "GeogEllipsoidGeoKey",
            ),
            (
                tm_keys(&[(2057, 34736, 1, 5)]),
                vec![0.0, 25.0, 1.0, 0.0, 0.0, 6378206.4],
                "GeogSemiMajorAxisGeoKey",
            ),
            (
                tm_keys(&[(3075, 0, 1, 8)]),
                TM_DOUBLES.to_vec(),
                "ProjCoordTransGeoKey",
            ),
            (
                tm_keys(&[(2051, 0, 1, 8903)]),
                TM_DOUBLES.to_vec(),
                "GeogPrimeMeridianGeoKey",
            ),
            (
                tm_keys(&[]).into_iter().filter(|k| k.0 != 3080).collect(),
                TM_DOUBLES.to_vec(),
                "ProjNatOriginLongGeoKey",
            ),
            (
                tm_keys(&[]).into_iter().filter(|k| k.0 != 3075).collect(),
                TM_DOUBLES.to_vec(),
                "ProjCoordTransGeoKey",
            ),
            (
                tm_keys(&[]).into_iter().filter(|k| k.0 != 3076).collect(),
                TM_DOUBLES.to_vec(),
                "ProjLinearUnitsGeoKey",
            ),
            (
                tm_keys(&[]),
                vec![0.0, 25.0, 0.0, 0.0, 0.0],
                "ProjScaleAtNatOriginGeoKey",
            ),
            (
                tm_keys(&[(3080, 0, 1, 25)]),
                TM_DOUBLES.to_vec(),
                "ProjNatOriginLongGeoKey",
            ),
        ];
        for (keys, doubles, name) in cases {
            let e = crs_of(&keys, &doubles).unwrap_err();
            assert!(e.key.contains(name), "expected {name}, got {e:?}");
        }
        // Missing angular units are fine when the GCS is EPSG:4326 (the NGI DEM), not otherwise.
        let k: Vec<_> = tm_keys(&[]).into_iter().filter(|k| k.0 != 2054).collect();
        assert_eq!(crs_of(&k, &TM_DOUBLES), Ok(expect));
        let k: Vec<_> = tm_keys(&[(2048, 0, 1, 32767), (2050, 0, 1, 6326)])
            .into_iter()
            .filter(|k| k.0 != 2054)
            .collect();
        assert!(
            crs_of(&k, &TM_DOUBLES)
                .unwrap_err()
                .key
                .contains("GeogAngularUnitsGeoKey")
        );
    }

    #[test]
    fn malformed_directories_are_errors() {
        assert!(GeoKeys::parse(&[1, 1], None, None).is_err());
        assert!(GeoKeys::parse(&[2, 1, 0, 0], None, None).is_err());
        assert!(GeoKeys::parse(&[1, 1, 0, 2, 1024, 0, 1, 1], None, None).is_err());
        let e = GeoKeys::parse(&dir(&[(3080, 34736, 1, 7)]), Some(&[1.0]), None).unwrap_err();
        assert!(e.tag.contains("GeoDoubleParamsTag"), "{e:?}");
        let e = GeoKeys::parse(&dir(&[(1026, 34737, 10, 0)]), None, None).unwrap_err();
        assert!(e.tag.contains("GeoAsciiParamsTag"), "{e:?}");
        let k = GeoKeys::parse(
            &dir(&[(1026, 34737, 6, 0), (1025, 0, 1, 7)]),
            None,
            Some("hello|x"),
        )
        .unwrap();
        assert_eq!(
            k.entries.get(&1026),
            Some(&GeoKeyValue::Ascii("hello".into()))
        );
        assert!(
            k.raster_type()
                .unwrap_err()
                .key
                .contains("GTRasterTypeGeoKey")
        );
    }

    #[test]
    fn geotransform_tags_and_pixel_is_point() {
        let sc = [2.0, 3.0, 0.0];
        let tp = [10.0, 20.0, 0.0, 1000.0, 5000.0, 0.0];
        let gt =
            geotransform_from_tags(Some(&sc), Some(&tp), None, RasterType::PixelIsArea).unwrap();
        assert_eq!(gt.coeffs(), [980.0, 2.0, 0.0, 5060.0, 0.0, -3.0]);
        assert_eq!(gt.pixel_to_map(10.0, 20.0), (1000.0, 5000.0));
        let gp =
            geotransform_from_tags(Some(&sc), Some(&tp), None, RasterType::PixelIsPoint).unwrap();
        // Pixel-is-point: the tiepoint is the centre of pixel (10, 20).
        assert_eq!(gp.pixel_to_map(10.5, 20.5), (1000.0, 5000.0));
        let m = [
            2.0, 0.5, 0.0, 100.0, //
            0.25, -3.0, 0.0, 200.0, //
            0.0, 0.0, 0.0, 0.0, //
            0.0, 0.0, 0.0, 1.0,
        ];
        let gm = geotransform_from_tags(None, None, Some(&m), RasterType::PixelIsArea).unwrap();
        assert_eq!(gm.coeffs(), [100.0, 2.0, 0.5, 200.0, 0.25, -3.0]);
        let gmp = geotransform_from_tags(None, None, Some(&m), RasterType::PixelIsPoint).unwrap();
        assert_eq!(gmp.pixel_to_map(0.5, 0.5), (100.0, 200.0));
        // Errors name the tag.
        let e = geotransform_from_tags(None, None, None, RasterType::PixelIsArea).unwrap_err();
        assert!(e.tag.contains("33550"));
        // A plain TIFF: the error says what to do.
        assert!(
            e.reason.contains("not georeferenced") && e.reason.contains("gdal_translate"),
            "{}",
            e.reason
        );
        let e = geotransform_from_tags(Some(&[0.0, 1.0]), Some(&tp), None, RasterType::PixelIsArea)
            .unwrap_err();
        assert!(e.tag.contains("ModelPixelScaleTag"));
        let e = geotransform_from_tags(Some(&sc), Some(&tp[..5]), None, RasterType::PixelIsArea)
            .unwrap_err();
        assert!(e.tag.contains("ModelTiepointTag"));
        let e = geotransform_from_tags(None, None, Some(&m[..12]), RasterType::PixelIsArea)
            .unwrap_err();
        assert!(e.tag.contains("ModelTransformationTag"));
        let gcps = [tp, tp].concat();
        assert!(geotransform_from_tags(None, Some(&gcps), None, RasterType::PixelIsArea).is_err());
    }

    #[test]
    fn loads_synthetic_files_of_each_sample_type() {
        let dirp = tempfile::tempdir().unwrap();
        let p = dirp.path().join("f32.tif");
        let mut tags = utm_tags(32633, 1);
        tags.push((Tag::GdalNodata, TagVal::Ascii("-9999")));
        let data: Vec<f32> = (0..12).map(|v| v as f32 * 1.5).collect();
        write_tiff::<colortype::Gray32Float>(
            &p,
            4,
            3,
            &data,
            &tags,
            Compression::Deflate(DeflateLevel::default()),
        );
        let r = load_geotiff(&p, None).unwrap();
        assert_eq!((r.width(), r.height(), r.bands()), (4, 3, 1));
        assert_eq!(
            r.crs(),
            Crs::Utm {
                zone: 33,
                north: true
            }
        );
        assert_eq!(
            r.transform().coeffs(),
            [500_000.0, 2.0, 0.0, 4_000_000.0, 0.0, -3.0]
        );
        assert_eq!(r.nodata(), Some(-9999.0));
        assert_eq!(r.source_type(), SampleType::F32);
        assert_eq!(r.sample(3, 2, 0), Some(16.5));

        // u16, LZW, pixel-is-point, ModelTransformation instead of scale + tiepoint.
        let p = dirp.path().join("u16.tif");
        let m = vec![
            2.0,
            0.0,
            0.0,
            500_000.0,
            0.0,
            -2.0,
            0.0,
            4_000_000.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            1.0,
        ];
        let tags = vec![
            (Tag::ModelTransformationTag, TagVal::F64(m)),
            (
                Tag::GeoKeyDirectoryTag,
                TagVal::U16(dir(&[
                    (1024, 0, 1, 1),
                    (1025, 0, 1, 2),
                    (3072, 0, 1, 32733),
                ])),
            ),
        ];
        let data: Vec<u16> = (0..6).map(|v| v * 1000).collect();
        write_tiff::<colortype::Gray16>(&p, 3, 2, &data, &tags, Compression::Lzw);
        let r = load_geotiff(&p, None).unwrap();
        assert_eq!(
            r.crs(),
            Crs::Utm {
                zone: 33,
                north: false
            }
        );
        assert_eq!(r.pixel_centre_to_map(0, 0), (500_000.0, 4_000_000.0));
        assert!(matches!(r.data(), RasterData::U16(_)));
        assert_eq!(r.sample(2, 1, 0), Some(5000.0));

        // i16, u8 RGB, f64, u32, i32: values survive.
        let p = dirp.path().join("i16.tif");
        write_tiff::<colortype::GrayI16>(
            &p,
            2,
            2,
            &[-5, 7, -32768, 32767],
            &utm_tags(32610, 1),
            Compression::Uncompressed,
        );
        let r = load_geotiff(&p, None).unwrap();
        assert_eq!(r.source_type(), SampleType::I16);
        assert_eq!(r.sample(0, 1, 0), Some(-32768.0));
        let p = dirp.path().join("rgb.tif");
        let rgb: Vec<u8> = (0..24).collect();
        write_tiff::<colortype::RGB8>(&p, 4, 2, &rgb, &utm_tags(32610, 1), Compression::Packbits);
        let r = load_geotiff(&p, None).unwrap();
        assert_eq!(r.bands(), 3);
        assert_eq!(r.sample(1, 1, 2), Some(((4 + 1) * 3 + 2) as f64));
        let p = dirp.path().join("f64.tif");
        write_tiff::<colortype::Gray64Float>(
            &p,
            2,
            2,
            &[0.25, -1e6, 3.5, 1e-3],
            &utm_tags(32610, 1),
            Compression::Lzw,
        );
        let r = load_geotiff(&p, None).unwrap();
        assert_eq!(r.source_type(), SampleType::F64);
        assert_eq!(r.sample(1, 0, 0), Some(-1e6));
        let p = dirp.path().join("u32.tif");
        write_tiff::<colortype::Gray32>(
            &p,
            2,
            1,
            &[7, 4_000_000],
            &utm_tags(32610, 1),
            Compression::Uncompressed,
        );
        assert_eq!(load_geotiff(&p, None).unwrap().sample(1, 0, 0), Some(4e6));
        let p = dirp.path().join("i32.tif");
        write_tiff::<colortype::GrayI32>(
            &p,
            2,
            1,
            &[-7, 40],
            &utm_tags(32610, 1),
            Compression::Uncompressed,
        );
        assert_eq!(load_geotiff(&p, None).unwrap().sample(0, 0, 0), Some(-7.0));
    }

    #[test]
    fn crs_override_rules() {
        let dirp = tempfile::tempdir().unwrap();
        let utm10 = Crs::Utm {
            zone: 10,
            north: true,
        };
        // No GeoKeys at all: error naming the directory tag, or the override.
        let p = dirp.path().join("nokeys.tif");
        let tags = vec![
            (Tag::ModelPixelScaleTag, TagVal::F64(vec![1.0, 1.0, 0.0])),
            (
                Tag::ModelTiepointTag,
                TagVal::F64(vec![0.0, 0.0, 0.0, 1.0, 2.0, 0.0]),
            ),
        ];
        write_tiff::<colortype::Gray8>(&p, 2, 2, &[1, 2, 3, 4], &tags, Compression::Uncompressed);
        let e = load_geotiff(&p, None).unwrap_err();
        let msg = e.to_string();
        assert!(
            msg.contains("nokeys.tif") && msg.contains("GeoKeyDirectoryTag (34735)"),
            "{msg}"
        );
        assert!(
            msg.contains("not georeferenced") && msg.contains("-a_srs"),
            "{msg}"
        );
        assert_eq!(load_geotiff(&p, Some(utm10)).unwrap().crs(), utm10);
        // Unsupported EPSG code: the override is used.
        let p = dirp.path().join("lcc.tif");
        write_tiff::<colortype::Gray8>(
            &p,
            2,
            2,
            &[1, 2, 3, 4],
            &utm_tags(2994, 1),
            Compression::Uncompressed,
        );
        let msg = load_geotiff(&p, None).unwrap_err().to_string();
        assert!(
            msg.contains("ProjectedCSTypeGeoKey (3072)") && msg.contains("2994"),
            "{msg}"
        );
        assert_eq!(load_geotiff(&p, Some(utm10)).unwrap().crs(), utm10);
        // Understood keys contradicting the override: conflict. Agreeing: fine.
        let p = dirp.path().join("utm.tif");
        write_tiff::<colortype::Gray8>(
            &p,
            2,
            2,
            &[1, 2, 3, 4],
            &utm_tags(32611, 1),
            Compression::Uncompressed,
        );
        assert!(matches!(
            load_geotiff(&p, Some(utm10)),
            Err(GeoTiffError::CrsConflict { .. })
        ));
        assert!(
            load_geotiff(
                &p,
                Some(Crs::Utm {
                    zone: 11,
                    north: true
                })
            )
            .is_ok()
        );
        // Malformed GeoKeyDirectory (declares 3 keys, holds 1): error, or the override.
        let p = dirp.path().join("badkeys.tif");
        let mut tags = utm_tags(32610, 1);
        tags[2] = (
            Tag::GeoKeyDirectoryTag,
            TagVal::U16(vec![1, 1, 0, 3, 1024, 0, 1, 1]),
        );
        write_tiff::<colortype::Gray8>(&p, 2, 2, &[1, 2, 3, 4], &tags, Compression::Uncompressed);
        let msg = load_geotiff(&p, None).unwrap_err().to_string();
        assert!(
            msg.contains("GeoKeyDirectoryTag (34735)") && msg.contains("declares 3 keys"),
            "{msg}"
        );
        assert_eq!(load_geotiff(&p, Some(utm10)).unwrap().crs(), utm10);
        // No georeferencing tags: error naming the tag, even with an override.
        let p = dirp.path().join("nogeo.tif");
        write_tiff::<colortype::Gray8>(&p, 2, 2, &[1, 2, 3, 4], &[], Compression::Uncompressed);
        let msg = load_geotiff(&p, Some(utm10)).unwrap_err().to_string();
        assert!(msg.contains("ModelPixelScaleTag (33550)"), "{msg}");
        // Bad nodata text.
        let p = dirp.path().join("badnodata.tif");
        let mut tags = utm_tags(32610, 1);
        tags.push((Tag::GdalNodata, TagVal::Ascii("none")));
        write_tiff::<colortype::Gray8>(&p, 2, 2, &[1, 2, 3, 4], &tags, Compression::Uncompressed);
        let msg = load_geotiff(&p, None).unwrap_err().to_string();
        assert!(msg.contains("GDAL_NODATA (42113)"), "{msg}");
    }

    #[test]
    fn truncated_and_non_tiff_files_are_errors() {
        let dirp = tempfile::tempdir().unwrap();
        let p = dirp.path().join("full.tif");
        let data: Vec<f32> = (0..64 * 64).map(|v| (v % 97) as f32).collect();
        write_tiff::<colortype::Gray32Float>(
            &p,
            64,
            64,
            &data,
            &utm_tags(32610, 1),
            Compression::Uncompressed,
        );
        let bytes = std::fs::read(&p).unwrap();
        assert!(load_geotiff(&p, None).is_ok());
        // Truncate at many lengths: always an error, never a panic.
        for cut in [
            0usize,
            3,
            8,
            20,
            100,
            1000,
            bytes.len() / 2,
            bytes.len() - 1,
        ] {
            let q = dirp.path().join(format!("cut{cut}.tif"));
            std::fs::write(&q, &bytes[..cut.min(bytes.len())]).unwrap();
            let e = load_geotiff(&q, None).unwrap_err();
            assert!(e.to_string().contains(&format!("cut{cut}.tif")), "{e}");
        }
        let q = dirp.path().join("text.tif");
        std::fs::write(&q, b"this is not a TIFF file at all, just text\n").unwrap();
        assert!(matches!(
            load_geotiff(&q, None),
            Err(GeoTiffError::Decode { .. })
        ));
        let q = dirp.path().join("missing.tif");
        assert!(matches!(
            load_geotiff(&q, None),
            Err(GeoTiffError::Io { .. })
        ));
    }
}
