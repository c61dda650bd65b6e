//! The view page: a job's model in 3D with its texture's versions side by
//! side, and the job list. The page is plain HTML and JavaScript over the
//! vendored three.js, embedded in the binary so that it works offline and
//! needs no build step. The service serves it (`service/view.rs`), and so
//! does `seamstress view` over a folder `process` wrote ([`serve_folder`]).

mod assets;
mod serve;

pub use assets::{asset, Asset, JOB_PAGE, LIST_PAGE};
pub use serve::{serve_folder, ViewError, LOCAL_JOB};
