//! Exploration noise on the policy's actions: Gaussian, each environment's
//! draws correlated in time by `actor.noise_correlation` (a first-order
//! autoregression, the discrete Ornstein–Uhlenbeck process) while keeping
//! the standard deviation `actor.noise`. Independent draws of σ 0.1 move
//! the trap a few px off its course in ten steps; a sphere is dodged by
//! 54. Correlated draws keep pushing one way for about 1 / (1 − ρ) steps,
//! so the data hold sidesteps the critics can learn from.

use tweezer_gym::SplitMix64;

/// Each environment's noise.
pub(crate) struct ExplorationNoise {
    sigma: f64,
    correlation: f64,
    draws: SplitMix64,
    /// Each environment's last noise.
    last: Vec<[f64; 2]>,
}

impl ExplorationNoise {
    /// Noise of standard deviation `sigma` with `correlation` from one step
    /// to the next, for `envs` environments, drawn from `draws`.
    pub(crate) fn new(sigma: f64, correlation: f64, envs: usize, draws: SplitMix64) -> Self {
        Self {
            sigma,
            correlation,
            draws,
            last: vec![[0.0; 2]; envs],
        }
    }

    /// Environment `env`'s noise for this step. Uncorrelated noise is
    /// `sigma` times a fresh normal draw per axis.
    pub(crate) fn next(&mut self, env: usize) -> [f64; 2] {
        let fresh = self.sigma * (1.0 - self.correlation * self.correlation).sqrt();
        let last = &mut self.last[env];
        for v in last.iter_mut() {
            *v = self.correlation * *v + fresh * self.draws.normal();
        }
        *last
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn series(correlation: f64) -> Vec<f64> {
        let mut noise = ExplorationNoise::new(0.3, correlation, 2, SplitMix64::new(5));
        (0..200_000).map(|_| noise.next(1)[0]).collect()
    }

    fn lag_one(x: &[f64]) -> (f64, f64) {
        let n = x.len() as f64;
        let mean = x.iter().sum::<f64>() / n;
        let var = x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
        let cov = x
            .windows(2)
            .map(|w| (w[0] - mean) * (w[1] - mean))
            .sum::<f64>()
            / (n - 1.0);
        (var.sqrt(), cov / var)
    }

    #[test]
    fn keeps_its_deviation_and_carries_its_correlation() {
        for rho in [0.0, 0.5, 0.9] {
            let (sd, r) = lag_one(&series(rho)[1000..]);
            assert!((sd - 0.3).abs() < 0.02, "ρ {rho}: σ {sd}");
            assert!((r - rho).abs() < 0.02, "ρ {rho}: lag-one correlation {r}");
        }
    }

    #[test]
    fn uncorrelated_noise_is_one_normal_draw_per_axis() {
        let mut noise = ExplorationNoise::new(0.1, 0.0, 3, SplitMix64::new(9));
        let mut draws = SplitMix64::new(9);
        for env in [0, 2, 1] {
            let [x, y] = noise.next(env);
            assert_eq!([x, y], [0.1 * draws.normal(), 0.1 * draws.normal()]);
        }
    }
}
