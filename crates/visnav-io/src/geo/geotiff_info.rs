//! GeoTIFF files' structure, georeferencing keys, info and errors (pure Rust on the `tiff` crate,
//! no GDAL), shared by the whole-image reader (`super::geotiff`) and the windowed one
//! (`super::window`).
//!
//! Reads the first image of a TIFF file (overviews in later IFDs are ignored): stripped or tiled,
//! chunky or planar, any compression the `tiff` crate decodes (none, deflate, LZW, packbits, JPEG;
//! YCbCr JPEG is converted to RGB with the JFIF equations),
//! horizontal/floating-point predictors, 8/16/32/64-bit integer and 32/64-bit float samples, any
//! number of bands. See `raster` for the sample storage and the pixel convention.
//!
//! Georeferencing follows the GeoTIFF 1.1 specification (OGC 19-008r4):
//!
//! * **Geotransform** from ModelPixelScaleTag (33550) + ModelTiepointTag (33922) (first tiepoint,
//!   as GDAL does), else ModelTransformationTag (34264). With raster space `(I, J)`:
//!   `x = X_tp + (I - I_tp) Sx`, `y = Y_tp - (J - J_tp) Sy`, or `x = m0 I + m1 J + m3`,
//!   `y = m4 I + m5 J + m7`. GTRasterTypeGeoKey (1025) = RasterPixelIsArea (1, default): raster
//!   `(0,0)` is the corner of the first pixel, which is already our convention;
//!   RasterPixelIsPoint (2): raster `(0,0)` is the centre of the first pixel, so the transform is
//!   shifted by half a pixel, `T_corner(c, r) = T_point(c - 0.5, r - 0.5)` (GDAL's default behaviour).
//! * **CRS** from GeoKeyDirectoryTag (34735) + GeoDoubleParamsTag (34736) + GeoAsciiParamsTag
//!   (34737), mapped onto [`Crs`]:
//!   - GTModelTypeGeoKey 2 (geographic) with GeographicTypeGeoKey 4326 -> `Crs::Geographic`;
//!   - ProjectedCSTypeGeoKey 32601-32660 / 32701-32760 (WGS84 UTM N/S) and 26901-26923 (NAD83 UTM
//!     N, treated as WGS84) -> `Crs::Utm`; 3857 (and the legacy 3785) -> `Crs::WebMercator`;
//!   - ProjectedCSTypeGeoKey 32767 (user-defined) with ProjectionGeoKey 16001-16060 / 16101-16160
//!     (UTM N/S) -> `Crs::Utm`, or ProjCoordTransGeoKey = CT_TransverseMercator (1) with
//!     ProjNatOriginLat/Long, ProjScaleAtNatOrigin, ProjFalseEasting/Northing ->
//!     `Crs::TransverseMercator`. The user-defined case requires a WGS84 datum (GeographicTypeGeoKey
//!     4326, or user-defined with GeogGeodeticDatumGeoKey 6326 / GeogEllipsoidGeoKey 7030 /
//!     WGS84 semi-axes), Greenwich prime meridian, degrees (GeogAngularUnitsGeoKey 9102) and metres
//!     (ProjLinearUnitsGeoKey 9001); anything else is an error naming the key.
//!   - Vertical keys (4096-4099) are not interpreted: heights are taken as they are stored.
//!
//! When the CRS keys are missing or not understood, `crs_override` (from config) is used and a
//! warning is logged; without an override that is an error. When the keys are understood and an
//! override is given that disagrees, that is an error too ([`GeoTiffError::CrsConflict`]), so a
//! config pointing at the wrong file cannot pass silently.
//!
//! Nodata comes from GDAL_NODATA (42113, ASCII; "nan" allowed). Malformed input never panics: all
//! decoder errors are returned, and as defence in depth a panic inside the `tiff` crate is caught
//! and reported as [`GeoTiffError::Decode`]. Pixels are decoded chunk by chunk (`read_chunk`, in
//! `super::window`, which `super::geotiff::load_geotiff` shares with the windowed reader) because
//! `Decoder::read_image_to_buffer` of tiff 0.11.3 panics on tiled planar files (e.g. the NGI
//! orthophotos).

use std::collections::BTreeMap;
use std::io::{Read, Seek};
use std::path::{Path, PathBuf};

use tiff::decoder::{ChunkType, Decoder, Limits};
use tiff::tags::Tag;

use visnav_core::geo::Crs;
use visnav_core::geo::raster::{Bounds, GeoTransform};

/// Largest decoded image accepted, bytes (all bands, in the file's sample type).
pub const MAX_DECODED_BYTES: usize = 2 << 30;

/// Errors loading a GeoTIFF. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum GeoTiffError {
    /// The file cannot be opened or read.
    #[error("{}: cannot read file: {cause}", .path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        cause: std::io::Error,
    },
    /// The TIFF structure or image data cannot be decoded (not a TIFF, truncated, unsupported
    /// compression, ...).
    #[error("{}: TIFF decoding failed: {reason}", .path.display())]
    Decode {
        /// The file.
        path: PathBuf,
        /// What is wrong, in words.
        reason: String,
    },
    /// A TIFF tag is missing, malformed or has an unsupported value.
    #[error("{}: tag {tag}: {reason}", .path.display())]
    Tag {
        /// The file.
        path: PathBuf,
        /// The TIFF tag, name and number.
        tag: String,
        /// What is wrong, in words.
        reason: String,
    },
    /// A GeoKey is missing, malformed or not understood, and no CRS override was given.
    #[error("{}: GeoKey {key}: {reason} (set a CRS override in the config if the file is right)", .path.display())]
    GeoKey {
        /// The file.
        path: PathBuf,
        /// The GeoKey, name and number.
        key: String,
        /// What is wrong, in words.
        reason: String,
    },
    /// A pixel window that is empty or not inside the image (`super::window`).
    #[error("{}: {reason}", .path.display())]
    Window {
        /// The file.
        path: PathBuf,
        /// What is wrong, in words.
        reason: String,
    },
    /// The file's CRS was understood but differs from the configured override.
    #[error("{}: the CRS in the file's GeoKeys ({}) contradicts the configured override ({})", .path.display(), describe_crs(.file), describe_crs(.configured))]
    CrsConflict {
        /// The file.
        path: PathBuf,
        /// The CRS the file states.
        file: Crs,
        /// The CRS the configuration gives.
        configured: Crs,
    },
}

/// A GeoKey problem, before the file name is attached.
#[derive(Debug, Clone, PartialEq)]
pub struct KeyError {
    /// Key name and number, e.g. "ProjLinearUnitsGeoKey (3076)".
    pub key: String,
    /// What is wrong, in words.
    pub reason: String,
}

impl KeyError {
    fn new(id: u16, reason: impl Into<String>) -> Self {
        Self {
            key: key_label(id),
            reason: reason.into(),
        }
    }
}

/// A tag problem, before the file name is attached.
#[derive(Debug, Clone, PartialEq)]
pub struct TagError {
    /// Tag name and number, e.g. "ModelPixelScaleTag (33550)".
    pub tag: String,
    /// What is wrong, in words.
    pub reason: String,
}

impl TagError {
    fn new(tag: &str, reason: impl Into<String>) -> Self {
        Self {
            tag: tag.to_string(),
            reason: reason.into(),
        }
    }
}

const TAG_PIXEL_SCALE: &str = "ModelPixelScaleTag (33550)";
const TAG_TIEPOINT: &str = "ModelTiepointTag (33922)";

/// What to do with a raster that has no place or no CRS (a plain TIFF, a scanned or exported
/// image): the tools are GDAL's, which every GIS installs (docs/first-flight.md, section 5).
pub const NOT_GEOREFERENCED_HINT: &str = "the file is not georeferenced: give it its place and CRS first, e.g. \
`gdal_translate -a_srs EPSG:32614 -a_ullr ULX ULY LRX LRY in.tif out.tif` with the corner \
coordinates its provider states, or `gdalwarp -t_srs EPSG:32614 in.tif out.tif` for a file with \
ground control points (docs/first-flight.md, \"A map of your area\")";
const TAG_TRANSFORMATION: &str = "ModelTransformationTag (34264)";
const TAG_KEY_DIRECTORY: &str = "GeoKeyDirectoryTag (34735)";
const TAG_DOUBLE_PARAMS: &str = "GeoDoubleParamsTag (34736)";
const TAG_ASCII_PARAMS: &str = "GeoAsciiParamsTag (34737)";
const TAG_NODATA: &str = "GDAL_NODATA (42113)";

/// GeoKey ids (GeoTIFF 1.1, section 7).
pub mod key {
    // Each is the key of the same name (in CamelCase, `GeoKey` appended) of the specification's
    // section 7, which documents it.
    #![allow(missing_docs)]
    pub const GT_MODEL_TYPE: u16 = 1024;
    pub const GT_RASTER_TYPE: u16 = 1025;
    pub const GT_CITATION: u16 = 1026;
    pub const GEOGRAPHIC_TYPE: u16 = 2048;
    pub const GEOG_CITATION: u16 = 2049;
    pub const GEOG_GEODETIC_DATUM: u16 = 2050;
    pub const GEOG_PRIME_MERIDIAN: u16 = 2051;
    pub const GEOG_LINEAR_UNITS: u16 = 2052;
    pub const GEOG_ANGULAR_UNITS: u16 = 2054;
    pub const GEOG_ELLIPSOID: u16 = 2056;
    pub const GEOG_SEMI_MAJOR_AXIS: u16 = 2057;
    pub const GEOG_SEMI_MINOR_AXIS: u16 = 2058;
    pub const GEOG_INV_FLATTENING: u16 = 2059;
    pub const GEOG_PRIME_MERIDIAN_LONG: u16 = 2061;
    pub const PROJECTED_CS_TYPE: u16 = 3072;
    pub const PROJ_CITATION: u16 = 3073;
    pub const PROJECTION: u16 = 3074;
    pub const PROJ_COORD_TRANS: u16 = 3075;
    pub const PROJ_LINEAR_UNITS: u16 = 3076;
    pub const PROJ_NAT_ORIGIN_LONG: u16 = 3080;
    pub const PROJ_NAT_ORIGIN_LAT: u16 = 3081;
    pub const PROJ_FALSE_EASTING: u16 = 3082;
    pub const PROJ_FALSE_NORTHING: u16 = 3083;
    pub const PROJ_CENTER_LONG: u16 = 3088;
    pub const PROJ_CENTER_LAT: u16 = 3089;
    pub const PROJ_CENTER_EASTING: u16 = 3090;
    pub const PROJ_CENTER_NORTHING: u16 = 3091;
    pub const PROJ_SCALE_AT_NAT_ORIGIN: u16 = 3092;
    pub const PROJ_SCALE_AT_CENTER: u16 = 3093;
    pub const VERTICAL_CS_TYPE: u16 = 4096;
    pub const VERTICAL_UNITS: u16 = 4099;
}

/// Human-readable "Name (id)" label of a GeoKey for error messages.
pub fn key_label(id: u16) -> String {
    let name = match id {
        key::GT_MODEL_TYPE => "GTModelTypeGeoKey",
        key::GT_RASTER_TYPE => "GTRasterTypeGeoKey",
        key::GT_CITATION => "GTCitationGeoKey",
        key::GEOGRAPHIC_TYPE => "GeographicTypeGeoKey",
        key::GEOG_CITATION => "GeogCitationGeoKey",
        key::GEOG_GEODETIC_DATUM => "GeogGeodeticDatumGeoKey",
        key::GEOG_PRIME_MERIDIAN => "GeogPrimeMeridianGeoKey",
        key::GEOG_LINEAR_UNITS => "GeogLinearUnitsGeoKey",
        key::GEOG_ANGULAR_UNITS => "GeogAngularUnitsGeoKey",
        key::GEOG_ELLIPSOID => "GeogEllipsoidGeoKey",
        key::GEOG_SEMI_MAJOR_AXIS => "GeogSemiMajorAxisGeoKey",
        key::GEOG_SEMI_MINOR_AXIS => "GeogSemiMinorAxisGeoKey",
        key::GEOG_INV_FLATTENING => "GeogInvFlatteningGeoKey",
        key::GEOG_PRIME_MERIDIAN_LONG => "GeogPrimeMeridianLongGeoKey",
        key::PROJECTED_CS_TYPE => "ProjectedCSTypeGeoKey",
        key::PROJ_CITATION => "PCSCitationGeoKey",
        key::PROJECTION => "ProjectionGeoKey",
        key::PROJ_COORD_TRANS => "ProjCoordTransGeoKey",
        key::PROJ_LINEAR_UNITS => "ProjLinearUnitsGeoKey",
        key::PROJ_NAT_ORIGIN_LONG => "ProjNatOriginLongGeoKey",
        key::PROJ_NAT_ORIGIN_LAT => "ProjNatOriginLatGeoKey",
        key::PROJ_FALSE_EASTING => "ProjFalseEastingGeoKey",
        key::PROJ_FALSE_NORTHING => "ProjFalseNorthingGeoKey",
        key::PROJ_CENTER_LONG => "ProjCenterLongGeoKey",
        key::PROJ_CENTER_LAT => "ProjCenterLatGeoKey",
        key::PROJ_CENTER_EASTING => "ProjCenterEastingGeoKey",
        key::PROJ_CENTER_NORTHING => "ProjCenterNorthingGeoKey",
        key::PROJ_SCALE_AT_NAT_ORIGIN => "ProjScaleAtNatOriginGeoKey",
        key::PROJ_SCALE_AT_CENTER => "ProjScaleAtCenterGeoKey",
        key::VERTICAL_CS_TYPE => "VerticalCSTypeGeoKey",
        key::VERTICAL_UNITS => "VerticalUnitsGeoKey",
        _ => "GeoKey",
    };
    format!("{name} ({id})")
}

/// Value of one GeoKey.
#[derive(Debug, Clone, PartialEq)]
pub enum GeoKeyValue {
    /// A SHORT stored in the directory itself (TIFFTagLocation 0), or SHORTs stored in the
    /// directory tag (location 34735).
    Shorts(Vec<u16>),
    /// DOUBLEs from GeoDoubleParamsTag.
    Doubles(Vec<f64>),
    /// ASCII from GeoAsciiParamsTag, with the trailing '|' separator removed.
    Ascii(String),
}

/// `3 SHORTs (1, 2, 3)`, `1 DOUBLE (0.5)`, `ASCII "WGS 84"` (messages; bounded by
/// `visnav_core::text`).
impl std::fmt::Display for GeoKeyValue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        /// At most this many values are listed.
        const SHOWN: usize = 8;
        let (kind, values): (&str, Vec<f64>) = match self {
            GeoKeyValue::Shorts(v) => ("SHORT", v.iter().map(|&x| f64::from(x)).collect()),
            GeoKeyValue::Doubles(v) => ("DOUBLE", v.clone()),
            GeoKeyValue::Ascii(t) => return write!(f, "ASCII {}", visnav_core::text::quote(t)),
        };
        let n = values.len();
        let mut shown: Vec<String> = values
            .iter()
            .take(SHOWN)
            .map(|&v| visnav_core::text::num(v))
            .collect();
        if n > SHOWN {
            shown.push("...".into());
        }
        let plural = if n == 1 { "" } else { "s" };
        write!(f, "{n} {kind}{plural} ({})", shown.join(", "))
    }
}

/// Parsed GeoKeyDirectory.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct GeoKeys {
    /// (KeyDirectoryVersion, KeyRevision, MinorRevision).
    pub version: (u16, u16, u16),
    /// The keys by number.
    pub entries: BTreeMap<u16, GeoKeyValue>,
}

/// Pixel-is-area vs pixel-is-point (GTRasterTypeGeoKey).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RasterType {
    /// Raster (0,0) is the top-left corner of the first pixel (GeoTIFF default).
    PixelIsArea,
    /// Raster (0,0) is the centre of the first pixel.
    PixelIsPoint,
}

impl GeoKeys {
    /// Parses a GeoKeyDirectoryTag with its parameter tags. Fails (naming the directory or the
    /// offending key) on a malformed directory; entries with an unknown location tag are skipped.
    pub fn parse(
        directory: &[u16],
        doubles: Option<&[f64]>,
        ascii: Option<&str>,
    ) -> Result<Self, TagError> {
        if directory.len() < 4 {
            return Err(TagError::new(
                TAG_KEY_DIRECTORY,
                format!(
                    "{} values, need at least the 4-value header",
                    directory.len()
                ),
            ));
        }
        if directory[0] != 1 {
            return Err(TagError::new(
                TAG_KEY_DIRECTORY,
                format!("KeyDirectoryVersion {} is not 1", directory[0]),
            ));
        }
        let n = usize::from(directory[3]);
        if directory.len() < 4 + 4 * n {
            return Err(TagError::new(
                TAG_KEY_DIRECTORY,
                format!(
                    "declares {n} keys but holds only {} values (need {})",
                    directory.len(),
                    4 + 4 * n
                ),
            ));
        }
        let mut keys = GeoKeys {
            version: (directory[0], directory[1], directory[2]),
            entries: BTreeMap::new(),
        };
        for e in directory[4..4 + 4 * n].chunks_exact(4) {
            let (id, loc, count, off) = (e[0], e[1], usize::from(e[2]), usize::from(e[3]));
            let value = match loc {
                0 => GeoKeyValue::Shorts(vec![e[3]]),
                34735 => {
                    let v = directory.get(off..off + count).ok_or_else(|| {
                        TagError::new(
                            TAG_KEY_DIRECTORY,
                            format!(
                                "{}: SHORT values {off}..{} out of range",
                                key_label(id),
                                off + count
                            ),
                        )
                    })?;
                    GeoKeyValue::Shorts(v.to_vec())
                }
                34736 => {
                    let v = doubles
                        .and_then(|d| d.get(off..off + count))
                        .ok_or_else(|| {
                            TagError::new(
                                TAG_DOUBLE_PARAMS,
                                format!(
                                    "{}: values {off}..{} missing (tag absent or too short)",
                                    key_label(id),
                                    off + count
                                ),
                            )
                        })?;
                    GeoKeyValue::Doubles(v.to_vec())
                }
                34737 => {
                    let v = ascii
                        .and_then(|a| a.as_bytes().get(off..off + count))
                        .ok_or_else(|| {
                            TagError::new(
                                TAG_ASCII_PARAMS,
                                format!(
                                    "{}: characters {off}..{} missing (tag absent or too short)",
                                    key_label(id),
                                    off + count
                                ),
                            )
                        })?;
                    let s = String::from_utf8_lossy(v);
                    GeoKeyValue::Ascii(s.trim_end_matches(['|', '\0']).to_string())
                }
                other => {
                    tracing::warn!(
                        key = %key_label(id),
                        location = other,
                        "GeoKey stored in an unknown tag; ignored"
                    );
                    continue;
                }
            };
            keys.entries.insert(id, value);
        }
        Ok(keys)
    }

    /// True when the key is present.
    pub fn has(&self, id: u16) -> bool {
        self.entries.contains_key(&id)
    }

    /// A single-SHORT key: `Ok(None)` when absent, error when present with another type or count.
    pub fn short(&self, id: u16) -> Result<Option<u16>, KeyError> {
        match self.entries.get(&id) {
            None => Ok(None),
            Some(GeoKeyValue::Shorts(v)) if v.len() == 1 => Ok(Some(v[0])),
            Some(other) => Err(KeyError::new(
                id,
                format!("expected one SHORT, found {other}"),
            )),
        }
    }

    /// A single-DOUBLE key: `Ok(None)` when absent, error when present with another type or count
    /// or a non-finite value.
    pub fn double(&self, id: u16) -> Result<Option<f64>, KeyError> {
        match self.entries.get(&id) {
            None => Ok(None),
            Some(GeoKeyValue::Doubles(v)) if v.len() == 1 && v[0].is_finite() => Ok(Some(v[0])),
            Some(other) => Err(KeyError::new(
                id,
                format!("expected one finite DOUBLE, found {other}"),
            )),
        }
    }

    /// Raster type (GTRasterTypeGeoKey), PixelIsArea when absent.
    pub fn raster_type(&self) -> Result<RasterType, KeyError> {
        match self.short(key::GT_RASTER_TYPE)? {
            None | Some(1) => Ok(RasterType::PixelIsArea),
            Some(2) => Ok(RasterType::PixelIsPoint),
            Some(v) => Err(KeyError::new(
                key::GT_RASTER_TYPE,
                format!("value {v} is neither RasterPixelIsArea (1) nor RasterPixelIsPoint (2)"),
            )),
        }
    }

    /// Maps the keys onto a [`Crs`] (rules in the module doc).
    pub fn crs(&self) -> Result<Crs, KeyError> {
        let model = match self.short(key::GT_MODEL_TYPE)? {
            Some(m) => m,
            None if self.has(key::PROJECTED_CS_TYPE) || self.has(key::PROJECTION) => 1,
            None if self.has(key::GEOGRAPHIC_TYPE) => 2,
            None => {
                return Err(KeyError::new(
                    key::GT_MODEL_TYPE,
                    "missing, and neither ProjectedCSTypeGeoKey nor GeographicTypeGeoKey is present",
                ));
            }
        };
        match model {
            1 => self.projected_crs(),
            2 => {
                self.check_wgs84_degrees()?;
                Ok(Crs::Geographic)
            }
            3 => Err(KeyError::new(
                key::GT_MODEL_TYPE,
                "ModelTypeGeocentric (3) is not supported",
            )),
            v => Err(KeyError::new(
                key::GT_MODEL_TYPE,
                format!("unknown model type {v}"),
            )),
        }
    }

    fn projected_crs(&self) -> Result<Crs, KeyError> {
        let pcs = self.short(key::PROJECTED_CS_TYPE)?;
        let crs = match pcs {
            Some(code @ 32601..=32660) => Crs::Utm {
                zone: (code - 32600) as u8, // ok: 1..=60 fits
                north: true,
            },
            Some(code @ 32701..=32760) => Crs::Utm {
                zone: (code - 32700) as u8, // ok: 1..=60 fits
                north: false,
            },
            Some(code @ 26901..=26923) => Crs::Utm {
                zone: (code - 26900) as u8, // ok: 1..=23 fits
                north: true,
            },
            Some(3857 | 3785) => Crs::WebMercator,
            Some(32767) | None => return self.user_defined_projected(),
            Some(code) => {
                return Err(KeyError::new(
                    key::PROJECTED_CS_TYPE,
                    format!(
                        "EPSG:{code} is not supported (supported: 326zz, 327zz, 269zz, 3857, \
                         or user-defined 32767 transverse Mercator on WGS84)"
                    ),
                ));
            }
        };
        self.check_linear_units_metres(false)?;
        Ok(crs)
    }

    fn user_defined_projected(&self) -> Result<Crs, KeyError> {
        self.check_wgs84_degrees()?;
        self.check_linear_units_metres(true)?;
        match self.short(key::PROJECTION)? {
            Some(code @ 16001..=16060) => {
                return Ok(Crs::Utm {
                    zone: (code - 16000) as u8, // ok: 1..=60 fits
                    north: true,
                });
            }
            Some(code @ 16101..=16160) => {
                return Ok(Crs::Utm {
                    zone: (code - 16100) as u8, // ok: 1..=60 fits
                    north: false,
                });
            }
            Some(32767) | None => {}
            Some(code) => {
                return Err(KeyError::new(
                    key::PROJECTION,
                    format!(
                        "projection code {code} is not supported (only UTM 160zz/161zz or user-defined 32767)"
                    ),
                ));
            }
        }
        match self.short(key::PROJ_COORD_TRANS)? {
            Some(1) => {}
            Some(code) => {
                return Err(KeyError::new(
                    key::PROJ_COORD_TRANS,
                    format!(
                        "coordinate transformation {code} is not supported (only CT_TransverseMercator = 1)"
                    ),
                ));
            }
            None => {
                return Err(KeyError::new(
                    key::PROJ_COORD_TRANS,
                    "missing for a user-defined projection",
                ));
            }
        }
        let param = |primary: u16, alt: u16| -> Result<f64, KeyError> {
            match self.double(primary)? {
                Some(v) => Ok(v),
                None => self.double(alt)?.ok_or_else(|| {
                    KeyError::new(
                        primary,
                        format!(
                            "missing (nor {}) for a user-defined transverse Mercator",
                            key_label(alt)
                        ),
                    )
                }),
            }
        };
        let lon0_deg = param(key::PROJ_NAT_ORIGIN_LONG, key::PROJ_CENTER_LONG)?;
        let lat0_deg = param(key::PROJ_NAT_ORIGIN_LAT, key::PROJ_CENTER_LAT)?;
        let k0 = param(key::PROJ_SCALE_AT_NAT_ORIGIN, key::PROJ_SCALE_AT_CENTER)?;
        let false_easting_m = param(key::PROJ_FALSE_EASTING, key::PROJ_CENTER_EASTING)?;
        let false_northing_m = param(key::PROJ_FALSE_NORTHING, key::PROJ_CENTER_NORTHING)?;
        if !(-180.0..=180.0).contains(&lon0_deg) {
            return Err(KeyError::new(
                key::PROJ_NAT_ORIGIN_LONG,
                format!("{lon0_deg} deg is outside [-180, 180]"),
            ));
        }
        if !(-90.0..=90.0).contains(&lat0_deg) {
            return Err(KeyError::new(
                key::PROJ_NAT_ORIGIN_LAT,
                format!("{lat0_deg} deg is outside [-90, 90]"),
            ));
        }
        if !(k0 > 0.5 && k0 < 2.0) {
            return Err(KeyError::new(
                key::PROJ_SCALE_AT_NAT_ORIGIN,
                format!("scale factor {k0} is implausible (expected about 1)"),
            ));
        }
        Ok(Crs::TransverseMercator {
            lat0_deg,
            lon0_deg,
            k0,
            false_easting_m,
            false_northing_m,
        })
    }

    /// ProjLinearUnitsGeoKey must be metres (9001). `required`: whether absence is an error.
    fn check_linear_units_metres(&self, required: bool) -> Result<(), KeyError> {
        match self.short(key::PROJ_LINEAR_UNITS)? {
            Some(9001) => Ok(()),
            None if !required => Ok(()),
            None => Err(KeyError::new(
                key::PROJ_LINEAR_UNITS,
                "missing for a user-defined projection (must be metres, 9001)",
            )),
            Some(v) => Err(KeyError::new(
                key::PROJ_LINEAR_UNITS,
                format!("unit {v} is not metres (9001)"),
            )),
        }
    }

    /// The geographic CRS must be WGS84 (4326 or a user-defined one with the WGS84 datum or
    /// ellipsoid), on Greenwich, with angles in degrees.
    fn check_wgs84_degrees(&self) -> Result<(), KeyError> {
        let gcs = self.short(key::GEOGRAPHIC_TYPE)?;
        match gcs {
            Some(4326) => {}
            Some(32767) | None => {
                let datum = self.short(key::GEOG_GEODETIC_DATUM)?;
                let ellipsoid = self.short(key::GEOG_ELLIPSOID)?;
                let axis = self.double(key::GEOG_SEMI_MAJOR_AXIS)?;
                let inv_f = self.double(key::GEOG_INV_FLATTENING)?;
                let semi_minor = self.double(key::GEOG_SEMI_MINOR_AXIS)?;
                match (datum, ellipsoid) {
                    (Some(6326), _) => {}
                    (Some(d), _) if d != 32767 => {
                        return Err(KeyError::new(
                            key::GEOG_GEODETIC_DATUM,
                            format!("datum EPSG:{d} is not WGS84 (6326)"),
                        ));
                    }
                    (_, Some(7030)) => {}
                    (_, Some(e)) if e != 32767 => {
                        return Err(KeyError::new(
                            key::GEOG_ELLIPSOID,
                            format!("ellipsoid EPSG:{e} is not WGS84 (7030)"),
                        ));
                    }
                    _ if axis.is_some() && (inv_f.is_some() || semi_minor.is_some()) => {}
                    _ => {
                        return Err(KeyError::new(
                            key::GEOGRAPHIC_TYPE,
                            if gcs.is_none() {
                                "missing: the datum cannot be established (must be WGS84)"
                            } else {
                                "user-defined without a WGS84 datum, ellipsoid or semi-axes"
                            },
                        ));
                    }
                }
            }
            Some(code) => {
                return Err(KeyError::new(
                    key::GEOGRAPHIC_TYPE,
                    format!("geographic CRS EPSG:{code} is not WGS84 (4326)"),
                ));
            }
        }
        // Explicit ellipsoid parameters must agree with WGS84 whatever the codes say.
        if let Some(a) = self.double(key::GEOG_SEMI_MAJOR_AXIS)?
            && (a - visnav_core::geo::wgs84::A_M).abs() > 1e-3
        {
            return Err(KeyError::new(
                key::GEOG_SEMI_MAJOR_AXIS,
                format!(
                    "{a} m is not the WGS84 semi-major axis {}",
                    visnav_core::geo::wgs84::A_M
                ),
            ));
        }
        if let Some(inv_f) = self.double(key::GEOG_INV_FLATTENING)?
            && (inv_f - 1.0 / visnav_core::geo::wgs84::F).abs() > 1e-6
        {
            return Err(KeyError::new(
                key::GEOG_INV_FLATTENING,
                format!(
                    "{inv_f} is not the WGS84 inverse flattening {}",
                    1.0 / visnav_core::geo::wgs84::F
                ),
            ));
        }
        if let Some(b) = self.double(key::GEOG_SEMI_MINOR_AXIS)?
            && (b - visnav_core::geo::wgs84::B_M).abs() > 1e-3
        {
            return Err(KeyError::new(
                key::GEOG_SEMI_MINOR_AXIS,
                format!(
                    "{b} m is not the WGS84 semi-minor axis {}",
                    visnav_core::geo::wgs84::B_M
                ),
            ));
        }
        match self.short(key::GEOG_PRIME_MERIDIAN)? {
            None | Some(8901) => {}
            Some(pm) => {
                return Err(KeyError::new(
                    key::GEOG_PRIME_MERIDIAN,
                    format!("prime meridian {pm} is not Greenwich (8901)"),
                ));
            }
        }
        if let Some(pm) = self.double(key::GEOG_PRIME_MERIDIAN_LONG)?
            && pm != 0.0
        {
            return Err(KeyError::new(
                key::GEOG_PRIME_MERIDIAN_LONG,
                format!("prime meridian longitude {pm} is not 0"),
            ));
        }
        match self.short(key::GEOG_ANGULAR_UNITS)? {
            Some(9102) => Ok(()),
            None if gcs == Some(4326) => Ok(()), // EPSG:4326 implies degrees
            None => Err(KeyError::new(
                key::GEOG_ANGULAR_UNITS,
                "missing for a user-defined geographic CRS (must be degrees, 9102)",
            )),
            Some(u) => Err(KeyError::new(
                key::GEOG_ANGULAR_UNITS,
                format!("unit {u} is not degrees (9102)"),
            )),
        }
    }
}

/// Builds the geotransform (corner convention) from the georeferencing tags.
/// Precedence as in GDAL: pixel scale + first tiepoint, else the model transformation.
pub fn geotransform_from_tags(
    pixel_scale: Option<&[f64]>,
    tiepoints: Option<&[f64]>,
    transformation: Option<&[f64]>,
    raster_type: RasterType,
) -> Result<GeoTransform, TagError> {
    let coeffs = match (pixel_scale, tiepoints, transformation) {
        (Some(sc), Some(tp), _) => {
            if sc.len() < 2 {
                return Err(TagError::new(
                    TAG_PIXEL_SCALE,
                    format!("{} values, need at least 2", sc.len()),
                ));
            }
            if tp.len() < 6 {
                return Err(TagError::new(
                    TAG_TIEPOINT,
                    format!("{} values, need at least 6", tp.len()),
                ));
            }
            let (sx, sy) = (sc[0], sc[1]);
            if !(sx.is_finite() && sy.is_finite()) || sx == 0.0 || sy == 0.0 {
                return Err(TagError::new(
                    TAG_PIXEL_SCALE,
                    format!("pixel scale ({sx}, {sy}) must be finite and non-zero"),
                ));
            }
            if tp[..6].iter().any(|v| !v.is_finite()) {
                return Err(TagError::new(TAG_TIEPOINT, "non-finite value"));
            }
            if tp.len() > 6 {
                tracing::warn!(
                    tiepoints = tp.len() / 6,
                    "several tiepoints with a pixel scale; using the first one (as GDAL does)"
                );
            }
            let (i, j, x, y) = (tp[0], tp[1], tp[3], tp[4]);
            [x - i * sx, sx, 0.0, y + j * sy, 0.0, -sy]
        }
        (_, _, Some(m)) => {
            if m.len() < 16 {
                return Err(TagError::new(
                    TAG_TRANSFORMATION,
                    format!("{} values, need 16 (4x4 matrix)", m.len()),
                ));
            }
            [m[3], m[0], m[1], m[7], m[4], m[5]]
        }
        (None, Some(tp), None) if tp.len() > 6 => {
            return Err(TagError::new(
                TAG_PIXEL_SCALE,
                "missing: ground control points (several tiepoints without a pixel scale) are not supported",
            ));
        }
        (None, _, None) => {
            return Err(TagError::new(
                TAG_PIXEL_SCALE,
                format!(
                    "missing: no georeferencing (neither ModelPixelScaleTag + ModelTiepointTag nor ModelTransformationTag); {NOT_GEOREFERENCED_HINT}"
                ),
            ));
        }
        (Some(_), None, None) => {
            return Err(TagError::new(
                TAG_TIEPOINT,
                "missing (a pixel scale alone does not locate the raster)",
            ));
        }
    };
    let [mut c0, c1, c2, mut c3, c4, c5] = coeffs;
    if raster_type == RasterType::PixelIsPoint {
        c0 -= 0.5 * (c1 + c2);
        c3 -= 0.5 * (c4 + c5);
    }
    GeoTransform::new([c0, c1, c2, c3, c4, c5]).map_err(|e| {
        TagError::new(
            if pixel_scale.is_some() && tiepoints.is_some() {
                TAG_PIXEL_SCALE
            } else {
                TAG_TRANSFORMATION
            },
            e.to_string(),
        )
    })
}

/// A CRS for messages: `UTM zone 10N (EPSG:32610)`, `EPSG:4326 (geographic, degrees)`, ...
pub fn describe_crs(c: &Crs) -> String {
    match *c {
        Crs::Geographic => "EPSG:4326 (WGS 84 geographic, degrees)".to_string(),
        Crs::Utm { zone, north } => format!(
            "UTM zone {zone}{} (EPSG:{})",
            if north { 'N' } else { 'S' },
            if north { 32600 } else { 32700 } + u32::from(zone)
        ),
        Crs::TransverseMercator {
            lat0_deg,
            lon0_deg,
            k0,
            false_easting_m,
            false_northing_m,
        } => format!(
            "transverse Mercator (lat0 {lat0_deg} deg, lon0 {lon0_deg} deg, k0 {k0}, false \
             easting {false_easting_m} m, false northing {false_northing_m} m)"
        ),
        Crs::WebMercator => "EPSG:3857 (web Mercator)".to_string(),
    }
}

/// Two CRSs denote the same system (transverse Mercator parameters compared with tolerances of
/// 1e-9 deg, 1e-9 in scale and 1 mm).
pub fn crs_equivalent(a: &Crs, b: &Crs) -> bool {
    match (a, b) {
        (
            Crs::TransverseMercator {
                lat0_deg: a0,
                lon0_deg: a1,
                k0: a2,
                false_easting_m: a3,
                false_northing_m: a4,
            },
            Crs::TransverseMercator {
                lat0_deg: b0,
                lon0_deg: b1,
                k0: b2,
                false_easting_m: b3,
                false_northing_m: b4,
            },
        ) => {
            (a0 - b0).abs() <= 1e-9
                && (a1 - b1).abs() <= 1e-9
                && (a2 - b2).abs() <= 1e-9
                && (a3 - b3).abs() <= 1e-3
                && (a4 - b4).abs() <= 1e-3
        }
        _ => a == b,
    }
}

/// Runs `f`, turning a panic (inside the `tiff` crate, on a malformed file) into
/// [`GeoTiffError::Decode`] naming `path`. Defence in depth: the crate must not panic on malformed
/// input, but if it does we return an error instead of bringing the daemon down.
pub(crate) fn guarded<T>(
    path: &Path,
    f: impl FnOnce() -> Result<T, GeoTiffError>,
) -> Result<T, GeoTiffError> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(_) => Err(GeoTiffError::Decode {
            path: path.to_path_buf(),
            reason: "the TIFF decoder panicked on this (malformed) file".into(),
        }),
    }
}

/// Everything known about a GeoTIFF's first image before its pixels are decoded.
#[derive(Debug, Clone, PartialEq)]
pub struct GeoTiffInfo {
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Samples per pixel.
    pub bands: usize,
    /// BitsPerSample of the first band.
    pub bits_per_sample: u16,
    /// Pixel (corner convention) -> map transform of the whole image.
    pub transform: GeoTransform,
    /// The horizontal CRS the GeoKeys (or the override) give.
    pub crs: Crs,
    /// GDAL_NODATA value (may be NaN; `Raster` stores a NaN nodata as `None`).
    pub nodata: Option<f64>,
    /// PlanarConfiguration = 2 (one plane per band) with more than one band.
    pub planar: bool,
    /// PhotometricInterpretation = YCbCr (6): samples are converted to RGB on reading.
    pub ycbcr: bool,
    /// Tiles (true) or strips (false).
    pub tiled: bool,
    /// Nominal chunk size, pixels: the tile size, or (width, rows per strip).
    pub chunk_width: usize,
    /// Nominal chunk height, pixels: the tile height or the rows per strip.
    pub chunk_height: usize,
}

impl GeoTiffInfo {
    /// Map-coordinate bounding box of the outer pixel edges (as [`Raster::bounds`](visnav_core::geo::raster::Raster::bounds)).
    pub fn bounds(&self) -> Bounds {
        self.transform.bounds(self.width, self.height)
    }
}

/// Reads the georeferencing tags, GeoKeys, nodata and image layout of the decoder's current image
/// (rules in the module doc). No pixel is decoded.
pub(crate) fn read_info<R: Read + Seek>(
    dec: &mut Decoder<R>,
    path: &Path,
    crs_override: Option<Crs>,
) -> Result<GeoTiffInfo, GeoTiffError> {
    let errs = InfoErrors { path };
    // The georeferencing first, so that a file that is no map fails before its layout is read.
    let tags = GeoTags::read(dec, &errs)?;
    let (transform, crs) = tags.georeferencing(&errs, crs_override)?;
    let nodata = tags.nodata(&errs)?;
    let layout = Layout::read(dec, &errs)?;
    Ok(GeoTiffInfo {
        width: layout.width,
        height: layout.height,
        bands: layout.bands,
        bits_per_sample: layout.bits_per_sample,
        transform,
        crs,
        nodata,
        planar: layout.planar == 2 && layout.bands > 1,
        ycbcr: layout.ycbcr,
        tiled: layout.tiled,
        chunk_width: layout.chunk_width,
        chunk_height: layout.chunk_height,
    })
}

/// The errors of [`read_info`], each naming the file.
struct InfoErrors<'a> {
    path: &'a Path,
}

impl InfoErrors<'_> {
    fn decode(&self, reason: String) -> GeoTiffError {
        GeoTiffError::Decode {
            path: self.path.to_path_buf(),
            reason,
        }
    }

    fn tag(&self, e: TagError) -> GeoTiffError {
        GeoTiffError::Tag {
            path: self.path.to_path_buf(),
            tag: e.tag,
            reason: e.reason,
        }
    }

    fn key(&self, e: KeyError) -> GeoTiffError {
        GeoTiffError::GeoKey {
            path: self.path.to_path_buf(),
            key: e.key,
            reason: e.reason,
        }
    }
}

/// A TIFF tag of DOUBLEs, if present.
fn f64_tag<R: Read + Seek>(
    dec: &mut Decoder<R>,
    tag: Tag,
    name: &str,
    errs: &InfoErrors,
) -> Result<Option<Vec<f64>>, GeoTiffError> {
    match dec.find_tag(tag) {
        Ok(None) => Ok(None),
        Ok(Some(v)) => v
            .into_f64_vec()
            .map(Some)
            .map_err(|e| errs.tag(TagError::new(name, format!("not a list of DOUBLEs: {e}")))),
        Err(e) => Err(errs.tag(TagError::new(name, e.to_string()))),
    }
}

/// A TIFF tag of ASCII text, if present.
fn ascii_tag<R: Read + Seek>(
    dec: &mut Decoder<R>,
    tag: Tag,
    name: &str,
    errs: &InfoErrors,
) -> Result<Option<String>, GeoTiffError> {
    match dec.find_tag(tag) {
        Ok(None) => Ok(None),
        Ok(Some(v)) => v
            .into_string()
            .map(Some)
            .map_err(|e| errs.tag(TagError::new(name, format!("not ASCII: {e}")))),
        Err(e) => Err(errs.tag(TagError::new(name, e.to_string()))),
    }
}

/// The georeferencing tags of an image, as stored.
struct GeoTags {
    pixel_scale: Option<Vec<f64>>,
    tiepoints: Option<Vec<f64>>,
    transformation: Option<Vec<f64>>,
    doubles: Option<Vec<f64>>,
    ascii: Option<String>,
    nodata_text: Option<String>,
    directory: Option<Vec<u16>>,
}

impl GeoTags {
    fn read<R: Read + Seek>(dec: &mut Decoder<R>, errs: &InfoErrors) -> Result<Self, GeoTiffError> {
        let pixel_scale = f64_tag(dec, Tag::ModelPixelScaleTag, TAG_PIXEL_SCALE, errs)?;
        let tiepoints = f64_tag(dec, Tag::ModelTiepointTag, TAG_TIEPOINT, errs)?;
        let transformation = f64_tag(dec, Tag::ModelTransformationTag, TAG_TRANSFORMATION, errs)?;
        let doubles = f64_tag(dec, Tag::GeoDoubleParamsTag, TAG_DOUBLE_PARAMS, errs)?;
        let ascii = ascii_tag(dec, Tag::GeoAsciiParamsTag, TAG_ASCII_PARAMS, errs)?;
        let nodata_text = ascii_tag(dec, Tag::GdalNodata, TAG_NODATA, errs)?;
        let directory = match dec.find_tag(Tag::GeoKeyDirectoryTag) {
            Ok(None) => None,
            Ok(Some(v)) => Some(v.into_u16_vec().map_err(|e| {
                errs.tag(TagError::new(
                    TAG_KEY_DIRECTORY,
                    format!("not a list of SHORTs: {e}"),
                ))
            })?),
            Err(e) => return Err(errs.tag(TagError::new(TAG_KEY_DIRECTORY, e.to_string()))),
        };
        Ok(Self {
            pixel_scale,
            tiepoints,
            transformation,
            doubles,
            ascii,
            nodata_text,
            directory,
        })
    }

    /// The pixel-to-map transform and the CRS (the file's, or the override where the file's keys
    /// are missing or not understood).
    fn georeferencing(
        &self,
        errs: &InfoErrors,
        crs_override: Option<Crs>,
    ) -> Result<(GeoTransform, Crs), GeoTiffError> {
        // A malformed directory counts as "keys not understood": the CRS override may stand in.
        let keys: Result<GeoKeys, KeyError> =
            match &self.directory {
                Some(d) => GeoKeys::parse(d, self.doubles.as_deref(), self.ascii.as_deref())
                    .map_err(|e| KeyError {
                        key: e.tag,
                        reason: e.reason,
                    }),
                None => Err(KeyError {
                    key: TAG_KEY_DIRECTORY.to_string(),
                    reason: format!(
                        "missing: the file has no GeoKeys (no CRS); {NOT_GEOREFERENCED_HINT}"
                    ),
                }),
            };
        let raster_type = match &keys {
            Ok(k) => k.raster_type().map_err(|e| errs.key(e))?,
            Err(_) => RasterType::PixelIsArea,
        };
        let transform = geotransform_from_tags(
            self.pixel_scale.as_deref(),
            self.tiepoints.as_deref(),
            self.transformation.as_deref(),
            raster_type,
        )
        .map_err(|e| errs.tag(e))?;
        let crs = resolve_crs(keys.and_then(|k| k.crs()), crs_override, errs)?;
        Ok((transform, crs))
    }

    /// GDAL_NODATA as a number.
    fn nodata(&self, errs: &InfoErrors) -> Result<Option<f64>, GeoTiffError> {
        let Some(t) = &self.nodata_text else {
            return Ok(None);
        };
        let t = t.trim_matches(|c: char| c == '\0' || c.is_whitespace());
        let v: f64 = t
            .parse()
            .map_err(|_| errs.tag(TagError::new(TAG_NODATA, format!("'{t}' is not a number"))))?;
        Ok(Some(v))
    }
}

/// The file's CRS against the configured override: the file's when they agree or none is
/// configured, the override where the file's keys fail, an error when both are given and differ.
fn resolve_crs(
    file_crs: Result<Crs, KeyError>,
    crs_override: Option<Crs>,
    errs: &InfoErrors,
) -> Result<Crs, GeoTiffError> {
    match (file_crs, crs_override) {
        (Ok(c), None) => Ok(c),
        (Ok(c), Some(o)) if crs_equivalent(&c, &o) => Ok(c),
        (Ok(c), Some(o)) => Err(GeoTiffError::CrsConflict {
            path: errs.path.to_path_buf(),
            file: c,
            configured: o,
        }),
        (Err(e), Some(o)) => {
            tracing::warn!(
                file = %errs.path.display(),
                key = %e.key,
                reason = %e.reason,
                crs = ?o,
                "GeoKeys not usable; using the configured CRS override"
            );
            Ok(o)
        }
        (Err(e), None) => Err(errs.key(e)),
    }
}

/// The image's size, samples and chunking.
struct Layout {
    width: usize,
    height: usize,
    bands: usize,
    planar: u16,
    bits_per_sample: u16,
    ycbcr: bool,
    tiled: bool,
    chunk_width: usize,
    chunk_height: usize,
}

impl Layout {
    fn read<R: Read + Seek>(dec: &mut Decoder<R>, errs: &InfoErrors) -> Result<Self, GeoTiffError> {
        let (w, h) = dec.dimensions().map_err(|e| errs.decode(e.to_string()))?;
        let (width, height) = (w as usize, h as usize);
        let bands = dec
            .find_tag_unsigned::<u16>(Tag::SamplesPerPixel)
            .map_err(|e| errs.tag(TagError::new("SamplesPerPixel (277)", e.to_string())))?
            .unwrap_or(1) as usize;
        let planar = dec
            .find_tag_unsigned::<u16>(Tag::PlanarConfiguration)
            .map_err(|e| errs.tag(TagError::new("PlanarConfiguration (284)", e.to_string())))?
            .unwrap_or(1);
        if width == 0 || height == 0 || bands == 0 {
            return Err(errs.decode(format!("invalid dimensions {width} x {height} x {bands}")));
        }
        let bits_per_sample = dec
            .find_tag_unsigned_vec::<u16>(Tag::BitsPerSample)
            .map_err(|e| errs.tag(TagError::new("BitsPerSample (258)", e.to_string())))?
            .and_then(|v| v.first().copied())
            .unwrap_or(1);
        let photometric = dec
            .find_tag_unsigned::<u16>(Tag::PhotometricInterpretation)
            .map_err(|e| {
                errs.tag(TagError::new(
                    "PhotometricInterpretation (262)",
                    e.to_string(),
                ))
            })?;
        let ycbcr = photometric == Some(6);
        if ycbcr && !(bands == 3 && bits_per_sample == 8) {
            return Err(errs.tag(TagError::new(
                "PhotometricInterpretation (262)",
                YCBCR_ONLY_RGB8,
            )));
        }
        let tiled = matches!(dec.get_chunk_type(), ChunkType::Tile);
        let (chunk_width, chunk_height) = chunk_size(dec, errs, tiled, width, height)?;
        Ok(Self {
            width,
            height,
            bands,
            planar,
            bits_per_sample,
            ycbcr,
            tiled,
            chunk_width,
            chunk_height,
        })
    }
}

/// The nominal chunk size, pixels: the tile size, or (width, rows per strip).
fn chunk_size<R: Read + Seek>(
    dec: &mut Decoder<R>,
    errs: &InfoErrors,
    tiled: bool,
    width: usize,
    height: usize,
) -> Result<(usize, usize), GeoTiffError> {
    let (chunk_width, chunk_height) = if tiled {
        let tw = dec
            .find_tag_unsigned::<u32>(Tag::TileWidth)
            .map_err(|e| errs.decode(format!("TileWidth (322): {e}")))?
            .ok_or_else(|| errs.decode("TileWidth (322) missing".into()))?;
        let th = dec
            .find_tag_unsigned::<u32>(Tag::TileLength)
            .map_err(|e| errs.decode(format!("TileLength (323): {e}")))?
            .ok_or_else(|| errs.decode("TileLength (323) missing".into()))?;
        (tw as usize, th as usize)
    } else {
        let rps = dec
            .find_tag_unsigned::<u32>(Tag::RowsPerStrip)
            .map_err(|e| errs.decode(format!("RowsPerStrip (278): {e}")))?
            .map_or(height, |r| (r as usize).min(height));
        (width, rps)
    };
    if chunk_width == 0 || chunk_height == 0 {
        return Err(errs.decode(format!(
            "chunk size {chunk_width} x {chunk_height} is invalid"
        )));
    }
    Ok((chunk_width, chunk_height))
}

/// Error text for a YCbCr image that is not 3-band 8-bit.
pub(crate) const YCBCR_ONLY_RGB8: &str = "YCbCr is supported only for 3-band 8-bit images";

/// Opens a `tiff` decoder with the crate limits raised to [`MAX_DECODED_BYTES`].
pub(crate) fn new_decoder<R: Read + Seek>(
    reader: R,
    path: &Path,
) -> Result<Decoder<R>, GeoTiffError> {
    let mut limits = Limits::default();
    limits.decoding_buffer_size = MAX_DECODED_BYTES;
    limits.intermediate_buffer_size = MAX_DECODED_BYTES;
    Ok(Decoder::new(reader)
        .map_err(|e| GeoTiffError::Decode {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?
        .with_limits(limits))
}

/// YCbCr -> RGB with the JFIF (ITU-R BT.601 full-range) equations that libjpeg and therefore
/// GDAL use for JPEG-in-TIFF: `R = Y + 1.402 (Cr-128)`, `G = Y - 0.344136 (Cb-128) - 0.714136
/// (Cr-128)`, `B = Y + 1.772 (Cb-128)`, rounded and clamped to 0..=255.
pub(crate) fn ycbcr_to_rgb_in_place(v: &mut [u8]) {
    for px in v.chunks_exact_mut(3) {
        let y = f32::from(px[0]);
        let cb = f32::from(px[1]) - 128.0;
        let cr = f32::from(px[2]) - 128.0;
        let to_u8 = |x: f32| x.round().clamp(0.0, 255.0) as u8; // ok: clamped to the u8 range
        px[0] = to_u8(y + 1.402 * cr);
        px[1] = to_u8(y - 0.344_136 * cb - 0.714_136 * cr);
        px[2] = to_u8(y + 1.772 * cb);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A key value reads as a count, a type and at most eight values, never Rust's debug form.
    #[test]
    fn key_values_read_as_counts_types_and_values() {
        assert_eq!(GeoKeyValue::Shorts(vec![7]).to_string(), "1 SHORT (7)");
        assert_eq!(
            GeoKeyValue::Doubles(vec![0.5, -2.0]).to_string(),
            "2 DOUBLEs (0.5, -2)"
        );
        let many = GeoKeyValue::Shorts((1..=10).collect());
        assert_eq!(many.to_string(), "10 SHORTs (1, 2, 3, 4, 5, 6, 7, 8, ...)");
        assert_eq!(
            GeoKeyValue::Ascii("WGS 84".into()).to_string(),
            "ASCII \"WGS 84\""
        );
    }
}
