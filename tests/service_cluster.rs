//! The service suite (`tests/service.rs`) again, with every server on the
//! cluster's stores: PostgreSQL for the jobs, an S3-compatible object store
//! (SeaweedFS) for the files (see `common/server.rs`). Tests of the
//! embedded stores' own failures say so and pass. Where the servers'
//! programs are missing, each test of the suite is here as an ignored one
//! that names them.

needs::module! {
    #[needs(postgres, seaweedfs)]
    #[path = "service.rs"]
    mod service;
}
