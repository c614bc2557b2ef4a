//! The paper's actor and critic networks (`docs/spec.md` §3) in Burn, shared by
//! the learner, the actors and the hardware agent.
//!
//! Both take the binary image observation `[batch, 1, height, width]` and the
//! target vector `[batch, 2]`; the critic also takes the action `[batch, 2]`.
//! Any resolution works: the flatten size follows. On a device without autodiff
//! (actors, the hardware agent, TD3 targets) BatchNorm uses its running
//! statistics.

mod actor;
mod critic;
mod encoder;
mod head;
mod images;
mod policy;
mod snapshot;

pub use actor::{Actor, ActorConfig};
pub use critic::{Critic, CriticConfig};
pub use encoder::{Encoder, EncoderConfig};
pub use head::{Head, HeadConfig};
pub use images::render_images;
pub use policy::{NetworkPolicy, PolicyFileError};
pub use snapshot::{
    ARCHITECTURE, SnapshotError, SnapshotInfo, decode, encode, file_sha256, read_info,
};
