//! The hardware agent's parts: the Thorlabs APT protocol its stage driver
//! speaks to the KDC101 controllers, and the driver, which keeps the stages
//! inside their limits.

pub mod apt;
pub mod stage;
