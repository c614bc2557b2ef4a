//! Whether two trainers computed the same update, for the test crates that
//! run one trainer beside another.

use tweezer_learner::training::td3::UpdateStats;

/// Asserts that update `i` has the same critic loss, mean Q and actor step
/// on both sides (`sides` names them), to `tolerance` relative to the
/// larger value (absolute below 1).
pub fn assert_same_update(
    i: usize,
    (a, b): (&UpdateStats, &UpdateStats),
    sides: [&str; 2],
    tolerance: f64,
) {
    let close = |what: &str, x: f64, y: f64| {
        assert!(
            (x - y).abs() <= tolerance * x.abs().max(y.abs()).max(1.0),
            "{what} of update {i}: {} {x} vs {} {y}",
            sides[0],
            sides[1]
        );
    };
    close("critic loss", a.critic_loss, b.critic_loss);
    close("mean Q", a.mean_q, b.mean_q);
    assert_eq!(
        a.actor_loss.is_some(),
        b.actor_loss.is_some(),
        "actor step of update {i}"
    );
    if let (Some(x), Some(y)) = (a.actor_loss, b.actor_loss) {
        close("actor loss", x, y);
    }
}
