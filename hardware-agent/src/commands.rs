//! The command line's one-shot commands; `serve` is the daemon (`daemon`).

pub mod bench;
pub mod cameras;
pub mod home;
pub mod run;
pub mod segment;
