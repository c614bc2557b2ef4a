//! The paper's actor and critic networks (`docs/spec.md` §3) in Burn, shared by
//! the learner, the actors and the hardware agent, and beside them networks
//! that read the sphere centres directly ([`SetActor`], [`SetCritic`]):
//! permutation-invariant, exact at any field of view, no rendering.
//!
//! The CNNs take the binary image observation `[batch, 1, height, width]`,
//! the set networks a padded set of sphere features ([`SetBatch`]); both
//! take the target vector `[batch, 2]`, and the critics also the action
//! `[batch, 2]`. Any resolution works: the flatten size follows.
//! [`Networks`] is what TD3 and the policies need of either; an
//! [`Architecture`] names one with its hyper-parameters. On a device without autodiff
//! (actors, the hardware agent, TD3 targets) BatchNorm uses its running
//! statistics.

mod actor;
mod approach;
mod architecture;
pub mod cpu_kernels;
mod critic;
pub mod critic_search;
mod encoder;
mod goal_frame;
mod head;
mod images;
mod networks;
mod policy;
mod set_actor;
mod set_critic;
mod set_encoder;
mod snapshot;
mod spheres;

pub use actor::{Actor, ActorConfig};
pub use architecture::{
    ActionJoin, Architecture, ArchitectureError, Frame, PAPER_ARCHITECTURE, Pooling,
    SET_ARCHITECTURE, SetShape, SphereInputs,
};
pub use critic::{Critic, CriticConfig};
pub use encoder::{Encoder, EncoderConfig};
pub use head::{Head, HeadConfig};
pub use images::render_images;
pub use networks::{AnyNetworks, Networks, PaperNetworks, SetNetworks};
pub use policy::{LoadError, NetworkPolicy, PolicyFileError};
pub use set_actor::{SetActor, SetActorConfig};
pub use set_critic::{SetCritic, SetCriticConfig, SetFeatures};
pub use set_encoder::{SetEncoder, SetEncoderConfig};
pub use snapshot::{
    CRITIC_PREFIXES, Decoded, SnapshotError, SnapshotInfo, decode, encode, encode_with_critics,
    file_sha256, read_info, without_critics,
};
pub use spheres::{Scene, SetBatch, SphereSets};
