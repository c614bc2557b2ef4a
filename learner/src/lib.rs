//! The learner: the replay table, TD3 and (with the learner issue's later
//! parts) the gRPC service that feeds them.

pub mod batch;
pub mod bench;
pub mod ingest;
pub mod limiter;
pub mod loopback;
pub mod replay;
pub mod td3;
