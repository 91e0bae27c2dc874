//! visnav-io's end-to-end tests, one module per file of this folder, built as one test binary:
//! bad input refused clearly (`bad_input`), every GeoTIFF form and the real data's files read as
//! GDAL reads them (`geodata`), windowed reading equal to the whole-image decode
//! (`geotiff_window`). `cargo test -p visnav-io` runs them; the real data's tests skip visibly
//! when `../shared/data` is absent.

mod bad_input;
mod geodata;
mod geotiff_window;
