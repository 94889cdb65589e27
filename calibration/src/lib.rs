//! Chessboard corners and camera and stereo calibration for microstereo's
//! `calibrate-stereo`: [`board::find_board`] finds a board's inner corners in an image,
//! [`calibrate::calibrate_stereo`] fits both cameras and their relative pose to pairs of
//! views, and the result is a [`rectify::StereoCalibration`], the model the rectifier and
//! the calibration file hold.

pub mod board;
pub mod calibrate;
pub mod lm;
pub mod pipette;
