//! `prl-track`: the `prl` command-line tool of the PRL-Track deployment toolchain, and the
//! pieces of it other programs (and the tests) use: reading frame sequences and decoding frames
//! the way the official code (OpenCV) does, reading benchmark datasets, and scoring trackers as
//! pysot-toolkit does (OPE).

mod calibration;
mod dataset;
mod frames;
pub mod longterm;
mod metrics;
pub mod occlusion;
pub mod ope;
mod sequence;
pub mod soak;
pub mod tracking;
pub mod video;

pub use calibration::{calibration_crops, CalibrationSpec, POSITION_JITTER, SCALE_JITTER};
pub use dataset::{detect, parse_pysot_json, Dataset, Format, Video, UAV123_ATTRIBUTES};
pub use frames::{
    decode_frame, decode_frame_bytes, frame_size, load_frame, read_frame, Damaged, MAX_FRAME_FILE_BYTES,
    MAX_FRAME_PIXELS,
};
pub use metrics::iou;
pub use sequence::{
    box_file_limit, init_box_from_groundtruth, parse_box, parse_boxes, parse_boxes_text, read_bounded,
    read_text_bounded, GroundTruth, InputError, Sequence, MAX_GROUNDTRUTH_FILES,
};
