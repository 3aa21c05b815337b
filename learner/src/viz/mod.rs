//! Pictures without a plotting stack: an indexed-colour canvas, line charts (PNG) and side
//! views of the crawler (GIF). Used by the `plot` and `render` binaries.

pub mod canvas;
pub mod chart;
pub mod render;

pub use canvas::{Canvas, Colour, GifWriter, SERIES};
pub use chart::{Area, Chart, Series, time_weighted_ema};
pub use render::{SideView, frame_stride};
