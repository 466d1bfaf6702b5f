//! `prl-track`: the `prl` command-line tool of the PRL-Track deployment toolchain, and the
//! pieces of it other programs (and the tests) use: reading frame sequences and decoding frames
//! the way the official code (OpenCV) does.

mod frames;
mod metrics;
mod sequence;

pub use frames::load_frame;
pub use metrics::iou;
pub use sequence::{init_box_from_groundtruth, parse_box, parse_boxes, InputError, Sequence};
