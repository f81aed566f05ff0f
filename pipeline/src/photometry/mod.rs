//! Aperture photometry with exact pixel-overlap geometry. (being implemented)
