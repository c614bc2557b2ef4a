//! TD3's pieces against hand-computed values, and the update's schedule.

mod agreement;

use agreement::assert_same_update;
use burn::module::{Module, ModuleVisitor, Param};
use burn::nn::{Linear, LinearConfig};
use burn::tensor::{Bytes, Device, Distribution, Tensor, TensorData};
use tweezer_gym::{EnvConfig, ImageConfig, Renderer, SplitMix64};
use tweezer_learner::training::module_updates::soft_update;
use tweezer_learner::training::td3::{
    Minibatch, Td3, Td3Config, smoothed_target_action, td_target,
};
use tweezer_nets::{Networks, PaperNetworks, Scene, SetBatch, SetNetworks, SetShape};

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_to_vec::<f32>().unwrap()
}

fn column(v: &[f32], device: &Device) -> Tensor<2> {
    Tensor::<2>::from_data(TensorData::new(v.to_vec(), [v.len(), 1]), device)
}

fn close(a: &[f32], b: &[f32]) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert!((x - y).abs() < 1e-6, "{a:?} vs {b:?}");
    }
}

#[test]
fn target_actions_are_smoothed_and_clipped() {
    let device = Device::flex();
    let action = Tensor::<2>::from_data(
        TensorData::new(vec![0.9f32, -0.2, 0.0, -0.95], [2, 2]),
        &device,
    );
    let noise = Tensor::<2>::from_data(
        TensorData::new(vec![0.3f32, 0.7, -0.6, -0.1], [2, 2]),
        &device,
    );
    // Noise clipped to ±0.5 first, then the sum to [-1, 1].
    let got = values(smoothed_target_action(action, noise, 0.5));
    close(&got, &[1.0, 0.3, -0.5, -1.0]);
}

#[test]
fn td_targets_take_the_smaller_critic_and_stop_at_termination() {
    let device = Device::flex();
    let y = td_target(
        column(&[1.0, -1.0, 1000.0], &device),
        column(&[0.0, 0.0, 1.0], &device),
        column(&[1.0, 1.0, 1.0], &device),
        column(&[10.0, -5.0, 50.0], &device),
        column(&[12.0, -7.0, 40.0], &device),
        0.86,
    );
    close(&values(y), &[1.0 + 0.86 * 10.0, -1.0 + 0.86 * -7.0, 1000.0]);
    // n-step: the bootstrap is discounted once per step taken.
    let y = td_target(
        column(&[2.0, 2.0], &device),
        column(&[0.0, 1.0], &device),
        column(&[3.0, 2.0], &device),
        column(&[10.0, 10.0], &device),
        column(&[10.0, 10.0], &device),
        0.5,
    );
    close(&values(y), &[2.0 + 0.125 * 10.0, 2.0]);
}

#[test]
fn soft_update_blends_every_parameter() {
    let device = Device::flex();
    let online: Linear = LinearConfig::new(3, 2).init(&device);
    let target: Linear = LinearConfig::new(3, 2).init(&device);
    // The target is shared here (cloned): it must be left as it was.
    let blended = soft_update(&online, target.clone(), 0.25);
    let w = |m: &Linear| values(m.weight.val());
    let b = |m: &Linear| values(m.bias.as_ref().unwrap().val());
    let expect = |on: Vec<f32>, old: Vec<f32>| -> Vec<f32> {
        on.iter()
            .zip(&old)
            .map(|(o, t)| 0.25 * o + 0.75 * t)
            .collect()
    };
    close(&w(&blended), &expect(w(&online), w(&target)));
    close(&b(&blended), &expect(b(&online), b(&target)));
    // τ = 1 copies; τ = 0 keeps.
    close(&w(&soft_update(&online, target.clone(), 1.0)), &w(&online));
    close(&w(&soft_update(&online, target.clone(), 0.0)), &w(&target));
    // Unshared, the target is written over in place: the same blend.
    let in_place = soft_update(&online, target, 0.25);
    close(&w(&in_place), &w(&blended));
    close(&b(&in_place), &b(&blended));
}

fn cnn(height: u32, width: u32) -> PaperNetworks {
    let env = EnvConfig {
        image: ImageConfig { width, height },
        ..EnvConfig::default()
    };
    PaperNetworks::new(Renderer::for_config(&env).unwrap())
}

fn batch(n: usize, device: &Device) -> Minibatch<Tensor<4>> {
    let image = || Tensor::<4>::random([n, 1, 64, 80], Distribution::Bernoulli(0.1), device);
    let pair = || Tensor::<2>::random([n, 2], Distribution::Uniform(-1.0, 1.0), device);
    Minibatch {
        input: image(),
        vector: pair(),
        action: pair(),
        reward: Tensor::<2>::random([n, 1], Distribution::Uniform(-1.0, 10.0), device),
        terminated: Tensor::<2>::zeros([n, 1], device),
        steps: Tensor::<2>::ones([n, 1], device),
        next_input: image(),
        next_vector: pair(),
        guide: Tensor::<2>::zeros([n, 2], device),
        guided: Tensor::<2>::zeros([n, 1], device),
    }
}

/// Random scenes of up to 20 spheres around a 1280 x 1024 field.
fn set_batch(n: usize, networks: &SetNetworks, device: &Device) -> Minibatch<SetBatch> {
    let mut rng = SplitMix64::new(n as u64);
    let scenes: Vec<Vec<[f32; 2]>> = (0..n)
        .map(|_| {
            let count = rng.integer_inclusive(0, 20) as usize;
            (0..count)
                .map(|_| {
                    [
                        rng.uniform(-27.0, 1307.0) as f32,
                        rng.uniform(-27.0, 1051.0) as f32,
                    ]
                })
                .collect()
        })
        .collect();
    let input = || networks.input(scenes.iter().map(|c| Scene::without_motion(c)), device);
    let pair = || Tensor::<2>::random([n, 2], Distribution::Uniform(-1.0, 1.0), device);
    Minibatch {
        input: input(),
        vector: pair(),
        action: pair(),
        reward: Tensor::<2>::random([n, 1], Distribution::Uniform(-1.0, 10.0), device),
        terminated: Tensor::<2>::zeros([n, 1], device),
        steps: Tensor::<2>::ones([n, 1], device),
        next_input: input(),
        next_vector: pair(),
        guide: Tensor::<2>::zeros([n, 2], device),
        guided: Tensor::<2>::zeros([n, 1], device),
    }
}

#[test]
fn the_actor_updates_every_second_step_and_losses_are_finite() {
    let device = Device::flex().autodiff();
    let mut td3 = Td3::new(Td3Config::default(), cnn(64, 80), &device).unwrap();
    let probe = batch(4, &device);
    let act = |td3: &Td3<PaperNetworks>| {
        values(
            td3.policy()
                .forward(probe.input.clone().valid(), probe.vector.clone().valid()),
        )
    };
    let a0 = act(&td3);
    let s1 = td3.update(batch(8, &device));
    assert!(s1.critic_loss.is_finite() && s1.mean_q.is_finite());
    assert_eq!(s1.actor_loss, None);
    assert_eq!(act(&td3), a0, "the actor must wait for the second update");
    let s2 = td3.update(batch(8, &device));
    assert!(s2.actor_loss.is_some_and(f64::is_finite));
    assert_ne!(act(&td3), a0, "the second update trains the actor");
    assert_eq!(td3.updates(), 2);
}

#[test]
fn bad_hyper_parameters_are_named() {
    let device = Device::flex().autodiff();
    for (config, field) in [
        (
            Td3Config {
                gamma: 1.5,
                ..Td3Config::default()
            },
            "td3.gamma",
        ),
        (
            Td3Config {
                policy_delay: 0,
                ..Td3Config::default()
            },
            "td3.policy_delay",
        ),
        (
            Td3Config {
                actor_lr: f64::NAN,
                ..Td3Config::default()
            },
            "td3.actor_lr",
        ),
        (
            Td3Config {
                noise_clip: -1.0,
                ..Td3Config::default()
            },
            "td3.noise_clip",
        ),
    ] {
        let err = Td3::new(config, cnn(64, 80), &device)
            .err()
            .expect("refused");
        assert!(err.to_string().contains(field), "{err}");
    }
}

/// A batch of small random images whose rewards are all `reward`.
fn batch_rewarded(reward: f32, device: &Device) -> Minibatch<Tensor<4>> {
    let image = || Tensor::<4>::random([4, 1, 16, 20], Distribution::Bernoulli(0.1), device);
    let pair = || Tensor::<2>::random([4, 2], Distribution::Uniform(-1.0, 1.0), device);
    Minibatch {
        input: image(),
        vector: pair(),
        action: pair(),
        reward: Tensor::<2>::full([4, 1], reward, device),
        terminated: Tensor::<2>::zeros([4, 1], device),
        steps: Tensor::<2>::ones([4, 1], device),
        next_input: image(),
        next_vector: pair(),
        guide: Tensor::<2>::zeros([4, 2], device),
        guided: Tensor::<2>::zeros([4, 1], device),
    }
}

/// An update whose critic loss is infinite (a reward whose square
/// overflows f32), judged by `guard`.
fn poisoned(
    td3: &mut Td3<PaperNetworks>,
    guard: &mut tweezer_learner::training::divergence::DivergenceGuard<PaperNetworks>,
) -> tweezer_learner::training::divergence::Verdict {
    let stats = td3.update(batch_rewarded(1e38, &td3_device()));
    assert!(!stats.critic_loss.is_finite());
    guard.check(td3, &stats)
}

fn td3_device() -> Device {
    Device::flex().autodiff()
}

/// Asserts that `td3` holds the state of `saved`'s copy: the same
/// networks and targets, BatchNorm running statistics included, and the
/// same updates from there without smoothing noise (the same Adam moments;
/// their records' bytes follow a hash map's order).
fn assert_same_state(td3: &Td3<PaperNetworks>, saved: &(std::path::PathBuf, Td3<PaperNetworks>)) {
    let networks = |td3: &Td3<PaperNetworks>| state(td3).into_iter().take(4).collect::<Vec<_>>();
    let (mut restored, mut copy) = (td3.clone(), saved.1.clone());
    assert!(
        networks(&restored) == networks(&copy),
        "not the state of {}",
        saved.0.display()
    );
    let batch = batch_rewarded(1.0, &td3_device());
    for td3 in [&mut restored, &mut copy] {
        td3.update(batch.clone());
        td3.update(batch.clone());
    }
    assert!(
        networks(&restored) == networks(&copy),
        "other Adam moments than {}",
        saved.0.display()
    );
}

/// Everything a checkpoint holds, BatchNorm running statistics and Adam's
/// moments included.
fn state(td3: &Td3<PaperNetworks>) -> Vec<(&'static str, Bytes)> {
    td3.save_state().unwrap()
}

#[test]
fn a_diverged_update_rolls_back_to_the_last_good_networks_and_repeated_ones_give_up() {
    use tweezer_learner::training::divergence::{
        DivergenceGuard, GOOD_RUN, MAX_ROLLBACKS, Rollback, Verdict,
    };
    let device = td3_device();
    let mut td3 = Td3::new(Td3Config::default(), cnn(16, 20), &device).unwrap();
    assert!(
        !Rollback::Auto.keeps_checkpoints(&td3),
        "small networks keep copies"
    );
    let mut guard = DivergenceGuard::with_copies(&td3);
    let probe = batch_rewarded(0.0, &device);
    let act = |td3: &Td3<PaperNetworks>| {
        values(
            td3.policy()
                .forward(probe.input.clone().valid(), probe.vector.clone().valid()),
        )
    };

    let (fresh, fresh_state) = (act(&td3), state(&td3));
    assert_eq!(
        poisoned(&mut td3, &mut guard),
        Verdict::RolledBack { lost: 1 }
    );
    assert_eq!((act(&td3), td3.updates()), (fresh.clone(), 0));
    assert!(state(&td3) == fresh_state, "the rollback left state behind");

    for _ in 0..GOOD_RUN {
        let stats = td3.update(batch_rewarded(1.0, &device));
        assert_eq!(guard.check(&mut td3, &stats), Verdict::Finite);
    }
    let (trained, trained_state) = (act(&td3), state(&td3));
    assert_ne!(trained, fresh);
    for _ in 1..MAX_ROLLBACKS {
        assert_eq!(
            poisoned(&mut td3, &mut guard),
            Verdict::RolledBack { lost: 1 }
        );
        assert_eq!((act(&td3), td3.updates()), (trained.clone(), GOOD_RUN));
        assert!(
            state(&td3) == trained_state,
            "the rollback left state behind"
        );
    }
    assert_eq!(poisoned(&mut td3, &mut guard), Verdict::GiveUp { lost: 1 });
    assert_eq!(act(&td3), trained);
}

#[test]
fn a_diverged_update_rolls_back_to_the_newest_checkpoint_then_to_older_ones() {
    use tweezer_learner::persistence::checkpoint::{CheckpointHeader, Checkpoints};
    use tweezer_learner::training::divergence::{DivergenceGuard, MAX_ROLLBACKS, Verdict};
    use tweezer_nets::Architecture;
    let device = td3_device();
    let dir = tempfile::tempdir().unwrap();
    let checkpoints = Checkpoints::open(dir.path(), 10).unwrap();
    let save = |td3: &Td3<PaperNetworks>, architecture: Architecture| {
        let header = CheckpointHeader {
            updates: td3.updates(),
            ..CheckpointHeader::new(architecture)
        };
        checkpoints
            .write(header, state(td3).into_iter().map(Ok))
            .unwrap()
    };
    let train = |td3: &mut Td3<PaperNetworks>, updates: usize| {
        for _ in 0..updates {
            assert!(
                td3.update(batch_rewarded(1.0, &device))
                    .critic_loss
                    .is_finite()
            );
        }
    };

    // Nothing to roll back to: said, not hidden.
    let mut td3 = Td3::new(Td3Config::default(), cnn(16, 20), &device).unwrap();
    let mut guard = DivergenceGuard::with_checkpoints(checkpoints.clone());
    match poisoned(&mut td3, &mut guard) {
        Verdict::Unrestorable { reason } => {
            assert!(reason.contains("no checkpoint"), "{reason}")
        }
        other => panic!("{other:?}"),
    }

    let mut td3 = Td3::new(noiseless(), cnn(16, 20), &device).unwrap();
    let mut guard = DivergenceGuard::with_checkpoints(checkpoints.clone());
    let architecture = td3.networks().architecture();
    let first = (save(&td3, architecture), td3.clone());
    train(&mut td3, 10);
    let second = (save(&td3, architecture), td3.clone());
    train(&mut td3, 2);
    // Newer, but of other networks: passed over.
    let other = save(
        &td3,
        Architecture::Paper {
            height: 8,
            width: 8,
        },
    );
    train(&mut td3, 3);

    assert_eq!(
        poisoned(&mut td3, &mut guard),
        Verdict::RolledBack { lost: 6 }
    );
    assert_eq!(td3.updates(), 10);
    assert_same_state(&td3, &second);
    assert!(other.exists());

    // Diverging again before a good run goes one checkpoint further back,
    // and the one that led to it is deleted.
    train(&mut td3, 4);
    assert_eq!(
        poisoned(&mut td3, &mut guard),
        Verdict::RolledBack { lost: 15 }
    );
    assert_eq!(td3.updates(), 0);
    assert_same_state(&td3, &first);
    assert!(!second.0.exists() && first.0.exists());

    for _ in 3..MAX_ROLLBACKS {
        assert_eq!(
            poisoned(&mut td3, &mut guard),
            Verdict::RolledBack { lost: 1 }
        );
    }
    assert_eq!(poisoned(&mut td3, &mut guard), Verdict::GiveUp { lost: 1 });
    assert_same_state(&td3, &first);
}

#[test]
fn the_set_networks_train_with_the_same_schedule() {
    let device = Device::flex().autodiff();
    let networks = SetNetworks::new(SetShape::new([1280, 1024]), [1280, 1024]);
    let mut td3 = Td3::new(Td3Config::default(), networks.clone(), &device).unwrap();
    let probe = set_batch(5, &networks, &device);
    let act = |td3: &Td3<SetNetworks>| {
        values(SetNetworks::act(
            &td3.policy(),
            probe.input.clone().valid(),
            probe.vector.clone().valid(),
        ))
    };
    let a0 = act(&td3);
    let s1 = td3.update(set_batch(16, &networks, &device));
    assert!(s1.critic_loss.is_finite() && s1.mean_q.is_finite());
    assert_eq!((s1.actor_loss, act(&td3)), (None, a0.clone()));
    let s2 = td3.update(set_batch(16, &networks, &device));
    assert!(s2.actor_loss.is_some_and(f64::is_finite));
    assert_ne!(act(&td3), a0, "the second update trains the actor");
    // Checkpointed state restores the same networks.
    let saved = td3.save_state().unwrap();
    let mut restored = Td3::new(Td3Config::default(), networks.clone(), &device).unwrap();
    restored
        .load_state(
            |name| saved.iter().find(|(n, _)| *n == name).map(|(_, b)| &b[..]),
            td3.updates(),
        )
        .unwrap();
    assert_eq!(act(&restored), act(&td3));
}

/// With `imitation`, the actor's loss pulls π towards the guide's action
/// on the rows that have one, and only there.
#[test]
fn the_actor_imitates_the_guide_where_there_is_one() {
    let device = Device::flex().autodiff();
    let networks = SetNetworks::new(SetShape::new([1280, 1024]), [1280, 1024]);
    let config = Td3Config {
        imitation: 5.0,
        policy_delay: 1,
        actor_lr: 1e-3,
        ..noiseless()
    };
    let start = Td3::new(config, networks.clone(), &device).unwrap();
    let probe = set_batch(32, &networks, &device);
    let goal = [0.6_f32, -0.4];
    let miss = |td3: &Td3<SetNetworks>| {
        let actions = values(SetNetworks::act(
            &td3.policy(),
            probe.input.clone().valid(),
            probe.vector.clone().valid(),
        ));
        let squared: f32 = (actions.chunks(2))
            .map(|a| (a[0] - goal[0]).powi(2) + (a[1] - goal[1]).powi(2))
            .sum();
        squared / 32.0
    };
    let trained = |guided: f32| {
        let mut td3 = start.clone();
        for _ in 0..60 {
            let mut batch = probe.clone();
            batch.guide =
                Tensor::<2>::from_data(TensorData::new(goal.repeat(32), [32, 2]), &device);
            batch.guided = Tensor::<2>::full([32, 1], guided, &device);
            td3.update(batch);
        }
        miss(&td3)
    };
    let (before, guided, unguided) = (miss(&start), trained(1.0), trained(0.0));
    assert!(
        guided < 0.25 * before && guided < 0.25 * unguided,
        "squared miss from the guide: {before} before, {guided} guided, {unguided} unguided"
    );
}

/// Every float a module holds, parameters and BatchNorm running statistics
/// alike, in visiting order.
struct Floats(Vec<f32>);

impl ModuleVisitor for Floats {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        self.0.extend(values(param.val()));
    }
}

fn floats<M: Module>(module: &M) -> Vec<f32> {
    let mut floats = Floats(Vec::new());
    module.visit(&mut floats);
    floats.0
}

/// TD3's defaults without target-policy noise: nothing random differs
/// between two trainers.
fn noiseless() -> Td3Config {
    Td3Config {
        policy_noise: 0.0,
        ..Td3Config::default()
    }
}

/// A rayon pool of `threads` threads.
fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
}

/// A trainer of the same networks with `td3`'s weights, targets and
/// optimiser states, target-policy noise off.
fn twin<N: Networks>(td3: &Td3<N>, device: &Device) -> Td3<N> {
    let mut twin = Td3::new(noiseless(), td3.networks().clone(), device).unwrap();
    let state = td3.save_state().unwrap();
    twin.load_state(
        |name| state.iter().find(|(n, _)| *n == name).map(|(_, b)| &b[..]),
        td3.updates(),
    )
    .unwrap();
    twin
}

/// Burn keeps a BatchNorm's running statistics per thread until something
/// reads them all; an update that runs on another thread than the last one
/// (rayon's workers take turns) must still continue the same running
/// averages. Two trainers from the same weights make the same updates, one
/// always on one thread, the other moving between two: each on one thread,
/// they compute the same numbers, bit for bit.
#[test]
fn batch_norm_statistics_do_not_depend_on_the_thread_an_update_runs_on() {
    let (one, other) = (pool(1), pool(1));
    let device = Device::flex().autodiff();
    let mut steady = Td3::new(noiseless(), cnn(64, 80), &device).unwrap();
    let mut moving = twin(&steady, &device);
    for i in 0..6 {
        let b = batch(8, &device);
        let a = one.install(|| steady.update(b.clone()));
        // A critic step on one thread, the actor step after it on another.
        let thread = if matches!(i % 4, 1 | 2) { &other } else { &one };
        let b = thread.install(|| moving.update(b));
        assert_eq!(a, b, "update {i}");
    }
    // The running statistics of the critics show in the targets above;
    // the actor's here.
    assert!(floats(&steady.policy()) == floats(&moving.policy()));
}

/// On the CPU backend the update runs independent passes side by side (the
/// TD target beside the online critics, Q1 beside Q2, the two critics'
/// backward passes, π beside Q1's encoder). On two threads it computes
/// what it computes on one, where they run one after the other, to float
/// rounding: for fresh networks of both architectures, several updates
/// each.
#[test]
fn passes_side_by_side_agree_with_passes_one_after_the_other() {
    let (one, two) = (pool(1), pool(2));
    let device = Device::flex().autodiff();
    fn agree<N: Networks>(
        mut sequential: Td3<N>,
        batches: impl Fn() -> Minibatch<N::Input>,
        one: &rayon::ThreadPool,
        two: &rayon::ThreadPool,
        device: &Device,
    ) {
        let mut parallel = twin(&sequential, device);
        for i in 0..6 {
            let b = batches();
            let a = one.install(|| sequential.update(b.clone()));
            let b = two.install(|| parallel.update(b));
            assert_same_update(i, (&a, &b), ["one thread", "two"], 1e-4);
        }
    }
    for _ in 0..16 {
        let cnn = Td3::new(noiseless(), cnn(64, 80), &device).unwrap();
        agree(cnn, || batch(8, &device), &one, &two, &device);
        let fov = EnvConfig::default().fov_px;
        let networks = SetNetworks::new(SetShape::new(fov), fov);
        let sets = Td3::new(noiseless(), networks.clone(), &device).unwrap();
        agree(
            sets,
            || set_batch(8, &networks, &device),
            &one,
            &two,
            &device,
        );
    }
}
