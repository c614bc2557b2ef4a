//! The hardware agent's parts: today the Thorlabs APT protocol its stage
//! driver speaks to the KDC101 controllers.

pub mod apt;
