//! The comparisons the retrieval experiment's claim rests on, over training seeds.
//!
//! The design is crossed: every policy (a condition trained with one seed) is judged on the
//! same rollout seeds. The unit that varies between conditions is the policy, not the rollout:
//! two policies of one condition differ by their training seed as much as conditions may differ
//! by their data, and rollouts of one policy are not independent evidence about the condition.
//! So each comparison is made on the policies' success rates:
//!
//! - an **exact permutation test**: under "the condition makes no difference" the policies'
//!   labels are exchangeable, so the observed difference of mean rates is ranked among the
//!   differences of every relabelling of the pooled policies into groups of the same sizes
//!   (two-sided). With few policies the smallest p it can give is coarse (3 + 3 policies: 20
//!   relabellings, p >= 0.1; 5 + 5: 252, p >= 0.008), and the table says so;
//! - a **bootstrap interval** of the difference: the policies of each condition resampled with
//!   replacement (seeded, so the summary is the same every time it is built).

use rand::{Rng, SeedableRng};
use serde::Serialize;

/// Condition `a` against condition `b` (does a beat b?), from their judged policies' rates.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Comparison {
    pub a: String,
    pub b: String,
    pub policies_a: usize,
    pub policies_b: usize,
    /// Mean success rate over each condition's policies.
    pub rate_a: f64,
    pub rate_b: f64,
    /// `rate_a - rate_b`.
    pub diff: f64,
    /// Two-sided exact permutation p over the policies' labels.
    pub p_permutation: f64,
    /// Relabellings ranked (every one, up to [`MAX_EXACT`]; a seeded sample of that many beyond).
    pub relabellings: u64,
    /// The smallest p this many policies can give.
    pub p_min: f64,
    /// 95% percentile bootstrap interval of `diff` (policies resampled within each condition).
    pub diff_ci95: [f64; 2],
}

/// Relabellings enumerated exactly up to this many; a seeded random sample of this size beyond.
pub const MAX_EXACT: u64 = 100_000;
const BOOTSTRAP: usize = 10_000;

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

fn choose(n: u64, k: u64) -> u64 {
    (0..k).fold(1u64, |acc, i| acc.saturating_mul(n - i) / (i + 1))
}

/// The comparison, when both conditions have at least one judged policy.
pub fn compare(a: &str, rates_a: &[f64], b: &str, rates_b: &[f64]) -> Option<Comparison> {
    if rates_a.is_empty() || rates_b.is_empty() {
        return None;
    }
    let (na, nb) = (rates_a.len(), rates_b.len());
    let observed = mean(rates_a) - mean(rates_b);
    let pooled: Vec<f64> = rates_a.iter().chain(rates_b).copied().collect();
    let total: f64 = pooled.iter().sum();
    // The difference of means when the policies in `group` are labelled a.
    let diff_of = |sum_a: f64| sum_a / na as f64 - (total - sum_a) / nb as f64;
    // (A relabelling at least as extreme, with room for the sums' rounding.)
    let extreme = |d: f64| d.abs() >= observed.abs() - 1e-9;
    let n = (na + nb) as u64;
    let exact = choose(n, na as u64);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let (hits, relabellings) = if exact <= MAX_EXACT {
        let mut hits = 0u64;
        for_each_subset(na + nb, na, &mut |subset| {
            let sum_a: f64 = subset.iter().map(|&i| pooled[i]).sum();
            hits += u64::from(extreme(diff_of(sum_a)));
        });
        (hits, exact)
    } else {
        let mut idx: Vec<usize> = (0..na + nb).collect();
        let mut hits = 0u64;
        for _ in 0..MAX_EXACT {
            // A partial Fisher-Yates shuffle: the first na are labelled a.
            for i in 0..na {
                let j = rng.random_range(i..na + nb);
                idx.swap(i, j);
            }
            let sum_a: f64 = idx[..na].iter().map(|&i| pooled[i]).sum();
            hits += u64::from(extreme(diff_of(sum_a)));
        }
        (hits, MAX_EXACT)
    };
    // The most extreme split, and its mirror when the groups are the same size.
    let p_min = if na == nb { 2.0 } else { 1.0 } / exact as f64;
    let mut diffs: Vec<f64> = (0..BOOTSTRAP)
        .map(|_| {
            let draw = |v: &[f64], rng: &mut rand_chacha::ChaCha8Rng| {
                (0..v.len()).map(|_| v[rng.random_range(0..v.len())]).sum::<f64>() / v.len() as f64
            };
            draw(rates_a, &mut rng) - draw(rates_b, &mut rng)
        })
        .collect();
    diffs.sort_by(f64::total_cmp);
    let at = |q: f64| diffs[((q * (BOOTSTRAP - 1) as f64).round() as usize).min(BOOTSTRAP - 1)];
    Some(Comparison {
        a: a.to_owned(),
        b: b.to_owned(),
        policies_a: na,
        policies_b: nb,
        rate_a: mean(rates_a),
        rate_b: mean(rates_b),
        diff: observed,
        p_permutation: hits as f64 / relabellings as f64,
        relabellings,
        p_min: p_min.min(1.0),
        diff_ci95: [at(0.025), at(0.975)],
    })
}

/// The spread of policies' success rates between training runs, estimated from a run's
/// conditions judged once each: the variance of their rates less the binomial variance of
/// their rollouts. Conditions that truly differ add to it, so it is an upper bound on the
/// spread between seeds of one condition (`None` with fewer than two conditions).
pub fn between_sd(counts: &[(u64, u64)]) -> Option<(f64, f64)> {
    let rates: Vec<f64> = counts.iter().filter(|(_, n)| *n > 0).map(|&(k, n)| k as f64 / n as f64).collect();
    if rates.len() < 2 {
        return None;
    }
    let m = mean(&rates);
    let var = rates.iter().map(|r| (r - m).powi(2)).sum::<f64>() / (rates.len() - 1) as f64;
    let binomial =
        mean(&counts.iter().filter(|(_, n)| *n > 0).map(|&(_, n)| m * (1.0 - m) / n as f64).collect::<Vec<_>>());
    Some((m, (var - binomial).max(0.0).sqrt()))
}

/// The power of [`compare`]'s permutation test (two-sided, level `alpha`) to find a true
/// difference `diff` between two conditions with `seeds` policies each, judged on `rollouts`
/// rollouts each: each policy's rate drawn around its condition's (`base` and `base + diff`)
/// with standard deviation `sd` (clipped to 0..1), its successes binomial; `sims` simulated
/// experiments (seeded).
pub fn power(base: f64, diff: f64, sd: f64, seeds: usize, rollouts: u64, alpha: f64, sims: usize) -> f64 {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let normal = |rng: &mut rand_chacha::ChaCha8Rng| {
        // Box-Muller.
        let (u, v): (f64, f64) = (rng.random_range(f64::EPSILON..1.0), rng.random());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    };
    let mut rejected = 0;
    for _ in 0..sims {
        let draw = |p: f64, rng: &mut rand_chacha::ChaCha8Rng| -> Vec<f64> {
            (0..seeds)
                .map(|_| {
                    let rate = (p + sd * normal(rng)).clamp(0.0, 1.0);
                    (0..rollouts).filter(|_| rng.random::<f64>() < rate).count() as f64 / rollouts as f64
                })
                .collect()
        };
        let (a, b) = (draw(base + diff, &mut rng), draw(base, &mut rng));
        if compare("a", &a, "b", &b).is_some_and(|c| c.p_permutation <= alpha) {
            rejected += 1;
        }
    }
    rejected as f64 / sims as f64
}

/// Calls `f` with every `k`-subset of `0..n` (in lexicographic order).
fn for_each_subset(n: usize, k: usize, f: &mut impl FnMut(&[usize])) {
    let mut idx: Vec<usize> = (0..k).collect();
    loop {
        f(&idx);
        // The rightmost index that can still move right.
        let Some(i) = (0..k).rev().find(|&i| idx[i] < n - k + i) else { return };
        idx[i] += 1;
        for j in i + 1..k {
            idx[j] = idx[j - 1] + 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_subset_is_visited_once() {
        let mut seen = Vec::new();
        for_each_subset(5, 2, &mut |s| seen.push(s.to_vec()));
        assert_eq!(seen.len(), 10);
        assert_eq!(seen[0], [0, 1]);
        assert_eq!(seen[9], [3, 4]);
        seen.dedup();
        assert_eq!(seen.len(), 10);
        assert_eq!(choose(10, 5), 252);
    }

    #[test]
    fn the_permutation_test_ranks_the_observed_split_among_all() {
        // Every a above every b: only this split and its mirror are as extreme, of C(6,3) = 20.
        let c = compare("a", &[0.8, 0.75, 0.7], "b", &[0.3, 0.35, 0.4]).unwrap();
        assert_eq!(c.relabellings, 20);
        assert!((c.p_permutation - 0.1).abs() < 1e-12, "{c:?}");
        assert!((c.p_min - 0.1).abs() < 1e-12);
        assert!((c.diff - 0.4).abs() < 1e-12);
        assert!(c.diff_ci95[0] > 0.3 && c.diff_ci95[1] < 0.5, "{c:?}");
        // Five a bove five: 2 of 252.
        let c = compare("a", &[0.9; 5], "b", &[0.1, 0.2, 0.3, 0.4, 0.5]).unwrap();
        assert!((c.p_permutation - 2.0 / 252.0).abs() < 1e-12, "{c:?}");
        // The same rates on both sides: nothing to tell them apart.
        let c = compare("a", &[0.5, 0.6, 0.4], "b", &[0.6, 0.4, 0.5]).unwrap();
        assert_eq!(c.p_permutation, 1.0);
        assert!(c.diff.abs() < 1e-12);
        assert!(c.diff_ci95[0] < 0.0 && c.diff_ci95[1] > 0.0, "{c:?}");
        // Interleaved groups: a p far from significance, computed by hand. a = {0.5, 0.3},
        // b = {0.4, 0.2}: diff 0.1; of the 6 splits, |diff| >= 0.1 for 4.
        let c = compare("a", &[0.5, 0.3], "b", &[0.4, 0.2]).unwrap();
        assert!((c.p_permutation - 4.0 / 6.0).abs() < 1e-12, "{c:?}");
        assert!(compare("a", &[], "b", &[0.5]).is_none());
    }

    #[test]
    fn the_power_grows_with_seeds_and_is_the_level_without_a_difference() {
        // No difference: rejections at about the level or below (the test is exact, and with
        // 3 + 3 policies it cannot reach p <= 0.05 at all).
        assert_eq!(power(0.4, 0.0, 0.07, 3, 40, 0.05, 200), 0.0);
        let none = power(0.4, 0.0, 0.07, 5, 40, 0.05, 400);
        assert!(none < 0.1, "{none}");
        let (five, eight) = (power(0.35, 0.2, 0.07, 5, 40, 0.05, 300), power(0.35, 0.2, 0.07, 8, 40, 0.05, 150));
        assert!(five > 0.5 && eight > five, "{five} {eight}");
        // The first run's seven conditions: 13 21 12 15 9 15 9 of 40.
        let (m, sd) = between_sd(&[(13, 40), (21, 40), (12, 40), (15, 40), (9, 40), (15, 40), (9, 40)]).unwrap();
        assert!((m - 94.0 / 280.0).abs() < 1e-12);
        assert!((0.06..0.08).contains(&sd), "{sd}");
        assert!(between_sd(&[(10, 40)]).is_none());
    }

    #[test]
    fn many_policies_are_sampled_not_enumerated() {
        let a: Vec<f64> = (0..12).map(|i| 0.5 + 0.01 * i as f64).collect();
        let b: Vec<f64> = (0..12).map(|i| 0.2 + 0.01 * i as f64).collect();
        let c = compare("a", &a, "b", &b).unwrap();
        assert_eq!(c.relabellings, MAX_EXACT, "C(24, 12) = 2.7 M relabellings are sampled");
        assert!(c.p_permutation < 1e-3, "{c:?}");
        // The same summary every time it is built.
        assert_eq!(compare("a", &a, "b", &b).unwrap(), c);
    }
}
