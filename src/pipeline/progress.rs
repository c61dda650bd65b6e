//! How a job reports where it is and takes a stop: a caller-supplied
//! [`Sink`], called between stages and textures. An `Err` from it stops the
//! job there, which then returns that [`Stop`].

/// Why a job stopped before its end.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stop {
    Canceled,
    TimedOut,
    ShuttingDown,
}

/// Where a job is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Progress<'a> {
    /// `load`, `process` (textures), `rewrite` (the model using the DDS).
    pub stage: &'a str,
    /// The texture being processed, and how many there are.
    pub texture: Option<(usize, usize)>,
    /// Of the whole job, 0 to 1.
    pub fraction: f64,
}

/// Receives a job's progress; an `Err` stops the job.
pub trait Sink {
    fn progress(&mut self, at: &Progress<'_>) -> Result<(), Stop>;
}

/// A closure is a sink.
impl<F: FnMut(&Progress<'_>) -> Result<(), Stop>> Sink for F {
    fn progress(&mut self, at: &Progress<'_>) -> Result<(), Stop> {
        self(at)
    }
}

/// Hears nothing, never stops.
pub struct NoSink;

impl Sink for NoSink {
    fn progress(&mut self, _: &Progress<'_>) -> Result<(), Stop> {
        Ok(())
    }
}
