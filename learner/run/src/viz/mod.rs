//! Pictures: line charts as PNG ([`charts`], drawn with `plotters` in an embedded font) for
//! `plot`, and side views of the crawler as GIF frames ([`render`] on the indexed-colour
//! [`canvas`]) for `render`.
//!
//! Why the GIF keeps a raster of its own: its frames are a few flat shapes in a 16-colour
//! palette, written straight into GIF's indexed format; a plotting library would draw RGB
//! frames only to quantise them back.

pub mod canvas;
pub mod charts;
pub mod render;

pub use canvas::{Canvas, Colour, GifWriter};
pub use render::{SideView, frame_stride};
