//! Pieces of the HTML reports of `demo` and `calibrate`: PSF mosaics (each kernel scaled to
//! its own peak, square-root display) and the page head.

use lensrig::image::{Image, Plane};
use lensrig::optics::psf_grid::PsfGrid;

/// The start of a report page: doctype, title and the shared style (`cell_padding` is the
/// table cells' CSS padding).
pub fn html_head(title: &str, cell_padding: &str, extra_style: &str) -> String {
    format!("<!doctype html><meta charset=utf-8><title>{title}</title><style>body{{font-family:sans-serif;margin:2em}}img{{image-rendering:pixelated;border:1px solid #ccc;max-width:45%}}td{{padding:{cell_padding}}}{extra_style}</style>")
}

/// Normalises each kernel of a mosaic to its own peak, for viewing.
pub fn psf_mosaic(grid: &PsfGrid, c: usize) -> Image {
    let k = grid.kernel_size;
    let mut m = Plane::new(grid.columns * (k + 2), grid.rows * (k + 2));
    for t in 0..grid.tile_count() {
        let mut kk = grid.kernels[c][t].clone();
        let mx = kk.max().max(1e-12);
        kk.scale(1.0 / mx);
        let kk = kk.map(|v| v.max(0.0).sqrt());
        m.paste(&kk, ((t % grid.columns) * (k + 2) + 1) as isize, ((t / grid.columns) * (k + 2) + 1) as isize);
    }
    Image::new(vec![m])
}
