//! Output files are never half-written: the one atomic writer of the workspace lives in
//! `sofipol_calib::atomic` (temporary file in the destination's directory, synced, renamed).
pub use sofipol_calib::atomic::{write_atomic, write_json_atomic};
