//! Many models through one command: which models a batch holds and where
//! each one's outputs go ([`discover()`]), whether a model's outputs are
//! still those of its inputs ([`cache`]), and what the batch did
//! ([`summary`]). The CLI's `process` runs a batch on these; the layout is
//! the contract a client writing the same tree must keep.

pub mod cache;
pub mod discover;
pub mod run;
pub mod summary;

pub use cache::{Stamp, STAMP_NAME};
pub use discover::{discover, BatchModel, DiscoverError};
pub use summary::{ModelOutcome, Summary};
