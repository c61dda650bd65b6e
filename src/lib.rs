//! Seamstress: seam erasure and seam-aware BC1 compression for glTF textures.
//!
//! Data flows one way: [`model`] (load glTF, bind textures, weld, find seams)
//! → [`seam`] (exact metric, erasure) → [`bc1`] (encode, seam-aware encode,
//! write DDS) → [`pipeline`] (one job: model in, files and report out);
//! [`container`] lays encoded blocks out as DDS and KTX2 files;
//! [`budget`] decides from a model's plan whether a job may run at all;
//! [`service`] runs the pipeline behind HTTP; [`batch`] runs many models
//! here, or through [`client`] on a server.

pub mod batch;
pub mod bc1;
pub mod bc7;
pub mod budget;
pub mod client;
pub mod container;
pub mod heap;
pub mod lod;
pub mod mips;
pub mod model;
pub mod picture;
pub mod pipeline;
pub mod plural;
pub mod resize;
pub mod seam;
pub mod service;
pub mod view;
