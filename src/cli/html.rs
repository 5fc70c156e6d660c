//! Pieces of the HTML reports of `demo` and `calibrate`: PSF mosaics (each kernel scaled to
//! its own peak, square-root display) and the page head.

use lensrig::image::Image;
use lensrig::optics::psf_grid::PsfGrid;

/// The start of a report page: doctype, title and the shared style (`cell_padding` is the
/// table cells' CSS padding).
pub fn html_head(title: &str, cell_padding: &str, extra_style: &str) -> String {
    format!("<!doctype html><meta charset=utf-8><title>{title}</title><style>body{{font-family:sans-serif;margin:2em}}img{{image-rendering:pixelated;border:1px solid #ccc;max-width:45%}}td{{padding:{cell_padding}}}{extra_style}</style>")
}

/// Each kernel of channel `c` scaled to its own peak, square-root display, as an image
/// ([`lensrig::report::psf_mosaic`]).
pub fn psf_mosaic(grid: &PsfGrid, c: usize) -> Image {
    Image::new(vec![lensrig::report::psf_mosaic(grid, c)])
}
