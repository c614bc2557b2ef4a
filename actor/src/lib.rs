//! The actor's configuration as a library: `experiment train` checks a
//! train file's `[actor]` table with it before it starts anything.

pub mod config;
