//! The command line's one-shot commands; `serve` is the daemon (`daemon`).

pub mod bench;
pub mod home;
pub mod run;
pub mod segment;
