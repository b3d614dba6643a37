//! The round-0 cache ([`OrderCache`]): each light position's order candidates fitted once for
//! every fold that holds its frames and for the final fit (the same fits, the same bits).

use super::*;

/// Which light position, in which model, a [`Candidates`] belongs to: its frames and anchors as
/// dataset frame numbers (a fold's registered-frame indices differ from the whole scan's), the
/// colour mode and the segments.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub(super) struct OrderKey {
    frames: [Vec<usize>; 3],
    anchors: [usize; 3],
    colour: ColourMode,
    segments: usize,
}

impl OrderKey {
    pub(super) fn of(
        choice: &ModelChoice,
        regs: &[RegisteredFrame],
        key: &crate::pipeline::select::GroupKey,
    ) -> Self {
        let frame = |l: &u32| regs.get(*l as usize).map_or(usize::MAX, |r| r.frame);
        OrderKey {
            frames: key.frames.each_ref().map(|f| f.iter().map(frame).collect()),
            anchors: key.anchors.each_ref().map(frame),
            colour: choice.colour,
            segments: choice.segments,
        }
    }
}

/// Round 0's candidate fits ([`Candidates`]), shared by the fits of one
/// [`crate::crossval::fit_scan_in`]: the cross-validation's fold fits and the final fit. A
/// light position's samples are those of its frames, whatever other frames a fit holds, so a
/// fold whose training frames hold all of them fits the very same candidates, bit for bit, as
/// the fit on every frame; they are fitted once ([`OrderCache::fill`]) instead of once per fold
/// and once more at the end. Only round 0 is shared: later rounds divide by the fold's own alpha.
/// The candidates depend on the fitter and the model choice too: a cache serves one fitter.
#[derive(Debug, Default)]
pub struct OrderCache {
    found: std::sync::Mutex<
        std::collections::HashMap<OrderKey, std::sync::Arc<Result<Candidates, FailReason>>>,
    >,
    hits: std::sync::atomic::AtomicUsize,
    fitted: std::sync::atomic::AtomicUsize,
    /// The homogeneous baselines ([`fit_baseline`]) by the keys of every light position they
    /// pool, in order: the same pooled samples, the same fit. The cross-validation's candidates
    /// of one fold (t1 off and on) share their training frames, and the baseline, fitted to the
    /// samples as captured, does not depend on t1: it was fitted once per candidate and fold,
    /// a twentieth of the 655,362-vertex pebble's CPU.
    baselines: std::sync::Mutex<
        std::collections::HashMap<Vec<OrderKey>, std::sync::Arc<Option<FittedBaseline>>>,
    >,
}

impl OrderCache {
    /// The candidates of `key`, fitted by `fit` unless known.
    pub(super) fn get_or_fit(
        &self,
        key: &OrderKey,
        fit: impl FnOnce() -> Result<Candidates, FailReason>,
    ) -> std::sync::Arc<Result<Candidates, FailReason>> {
        use std::sync::atomic::Ordering::Relaxed;
        let (c, hit) = memoised(&self.found, key, fit);
        if hit { &self.hits } else { &self.fitted }.fetch_add(1, Relaxed);
        c
    }

    /// Fits the candidates of every group of a selection (`regs`, `groups`: the fit on every
    /// frame) with the run's model choice, the groups in parallel, before the folds start, so
    /// that the folds, running side by side, find them instead of fitting them each.
    pub fn fill(
        &self,
        ctx: &Context,
        regs: &[RegisteredFrame],
        groups: &Groups,
        fitter: &dyn Fitter,
        progress: &dyn Progress,
    ) {
        let (Some(_), Some(max_n)) = (ctx.opts.order, fitter.max_terms()) else {
            return;
        };
        let choice = &ctx.opts.model;
        progress.start("fit (round 1 candidates)", groups.keys.len() as u64);
        groups.keys.par_iter().for_each(|key| {
            let k = OrderKey::of(choice, regs, key);
            if let Ok((data, _)) = group_samples(ctx, regs, key) {
                self.get_or_fit(&k, || order_candidates(&data, choice, fitter, max_n));
            }
            progress.inc(1);
        });
    }

    /// The baseline of the selection `regs`, `groups` with the run's model choice, fitted by
    /// `fit` unless a fit of the same light positions' samples made it already.
    pub(super) fn baseline(
        &self,
        ctx: &Context,
        regs: &[RegisteredFrame],
        groups: &Groups,
        fit: impl FnOnce() -> Option<FittedBaseline>,
    ) -> Option<FittedBaseline> {
        let key: Vec<OrderKey> = groups
            .keys
            .iter()
            .map(|k| OrderKey::of(&ctx.opts.model, regs, k))
            .collect();
        memoised(&self.baselines, &key, fit).0.as_ref().clone()
    }

    /// Light positions whose candidates were fitted, and lookups that found them fitted.
    pub fn counts(&self) -> (usize, usize) {
        use std::sync::atomic::Ordering::Relaxed;
        (self.fitted.load(Relaxed), self.hits.load(Relaxed))
    }
}

/// The value of `key` in `map`, made by `make` unless there (without the lock held: fits run
/// side by side, and two that race make the same value, the first kept); second: whether it
/// was there.
fn memoised<K: Eq + std::hash::Hash + Clone, V>(
    map: &std::sync::Mutex<std::collections::HashMap<K, std::sync::Arc<V>>>,
    key: &K,
    make: impl FnOnce() -> V,
) -> (std::sync::Arc<V>, bool) {
    let known = map
        .lock()
        .ok()
        .and_then(|m| m.get(key).map(std::sync::Arc::clone));
    if let Some(v) = known {
        return (v, true);
    }
    let v = std::sync::Arc::new(make());
    if let Ok(mut m) = map.lock() {
        m.entry(key.clone())
            .or_insert_with(|| std::sync::Arc::clone(&v));
    }
    (v, false)
}
