//! The recursive GP and the RGP-dKF as Python classes, one file each: `RecursiveGPCore`
//! (`recursive_gp.rs`) and `RGPEKFCore` (`ekf.rs`, reading the user's results with `read.rs`);
//! the Python classes in gpmhe/rgp/ validate input and call these once per step.

mod ekf;
mod read;
mod recursive_gp;

pub(crate) use ekf::RgpEkfCore;
pub(crate) use recursive_gp::RgpCore;
