//! Exact `f32` log-odds of the 512 voxels of a block, stored by how many distinct values they
//! hold: one value for the whole block (free space after a few scans, and never-updated blocks),
//! a palette of up to 256 exact values with one byte per voxel (the common case: a block holds a
//! handful of hit/miss counts), or a flat array when a block holds more distinct values.
//!
//! Values are compared by their bits, so what is read back is exactly what was stored.

use crate::grid::{mask_test, Mask, BLOCK_VOXELS, EMPTY};

/// Largest palette; one more distinct value makes the block flat.
const MAX_PALETTE: usize = 256;
/// Palettes at least this long are compacted (unused entries dropped) before an update.
const COMPACT_AT: usize = 48;

/// One log-odds update rule: add `hit` or `miss`, then clamp to `[lo, hi]`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Step {
    pub hit: f32,
    pub miss: f32,
    pub lo: f32,
    pub hi: f32,
}

impl Step {
    #[inline(always)]
    fn apply(self, v: f32, is_hit: bool) -> f32 {
        (v + if is_hit { self.hit } else { self.miss }).clamp(self.lo, self.hi)
    }
}

/// Palette storage: `values[idx[l]]` is voxel `l`'s value.
#[derive(Clone)]
pub(crate) struct Palette {
    values: Vec<f32>,
    idx: [u8; BLOCK_VOXELS],
}

impl Palette {
    fn find_or_push(&mut self, v: f32) -> Option<u8> {
        let bits = v.to_bits();
        if let Some(i) = self.values.iter().position(|x| x.to_bits() == bits) {
            return Some(i as u8);
        }
        if self.values.len() >= MAX_PALETTE {
            return None;
        }
        self.values.push(v);
        Some((self.values.len() - 1) as u8)
    }

    /// Drops the entries no voxel uses.
    fn compact(&mut self) {
        let mut used = [false; MAX_PALETTE];
        for &i in &self.idx {
            used[usize::from(i)] = true;
        }
        let mut remap = [0u8; MAX_PALETTE];
        let mut kept = Vec::with_capacity(self.values.len());
        for (i, &v) in self.values.iter().enumerate() {
            if used[i] {
                remap[i] = kept.len() as u8;
                kept.push(v);
            }
        }
        for i in &mut self.idx {
            *i = remap[usize::from(*i)];
        }
        self.values = kept;
    }

    fn flatten(&self) -> Box<[f32; BLOCK_VOXELS]> {
        let mut out = Box::new([0.0; BLOCK_VOXELS]);
        for (o, &i) in out.iter_mut().zip(&self.idx) {
            *o = self.values[usize::from(i)];
        }
        out
    }

    /// The one value of the block, when every voxel holds the same.
    fn single(&self) -> Option<f32> {
        let first = self.idx[0];
        self.idx
            .iter()
            .all(|&i| i == first)
            .then(|| self.values[usize::from(first)])
    }
}

/// Log-odds of one block's voxels.
#[derive(Clone)]
pub(crate) enum Values {
    /// Every voxel holds this value.
    Uniform(f32),
    Palette(Box<Palette>),
    Flat(Box<[f32; BLOCK_VOXELS]>),
}

/// The voxels of `known` for which `holds` is true (generic, so `holds` is inlined into the
/// loop over each word's 64 voxels).
#[inline]
fn gather_bits(known: &Mask, holds: impl Fn(usize) -> bool) -> Mask {
    let mut out = EMPTY;
    for (w, (o, &k)) in out.iter_mut().zip(known).enumerate() {
        if k == 0 {
            continue;
        }
        let word = (0..64).fold(0u64, |acc, b| acc | u64::from(holds(w * 64 + b)) << b);
        *o = word & k;
    }
    out
}

impl Default for Values {
    fn default() -> Self {
        Values::Uniform(0.0)
    }
}

impl Values {
    #[inline]
    pub(crate) fn get(&self, l: usize) -> f32 {
        match self {
            Values::Uniform(v) => *v,
            Values::Palette(p) => p.values[usize::from(p.idx[l])],
            Values::Flat(a) => a[l],
        }
    }

    /// Heap bytes beyond the enum itself.
    pub(crate) fn heap_bytes(&self) -> usize {
        match self {
            Values::Uniform(_) => 0,
            Values::Palette(p) => std::mem::size_of::<Palette>() + p.values.capacity() * 4,
            Values::Flat(_) => std::mem::size_of::<[f32; BLOCK_VOXELS]>(),
        }
    }

    /// Distinct values and per-voxel indices (uniform: one value, all indices 0; flat: `None`).
    pub(crate) fn palette(&self) -> Option<(&[f32], Option<&[u8; BLOCK_VOXELS]>)> {
        match self {
            Values::Uniform(v) => Some((std::slice::from_ref(v), None)),
            Values::Palette(p) => Some((&p.values, Some(&p.idx))),
            Values::Flat(_) => None,
        }
    }

    /// Storage from a palette and the index of each voxel in `known` (in bit order); the other
    /// voxels hold 0. `None` when an index is out of the palette.
    pub(crate) fn from_palette(values: Vec<f32>, known: &Mask, indices: &[u8]) -> Option<Values> {
        let mut p = Box::new(Palette {
            values,
            idx: [0; BLOCK_VOXELS],
        });
        let known_all = known.iter().all(|&w| w == u64::MAX);
        let zero = if known_all { 0 } else { p.find_or_push(0.0)? };
        if known_all && indices.len() == BLOCK_VOXELS {
            p.idx.copy_from_slice(indices);
        } else {
            p.idx = [zero; BLOCK_VOXELS];
            let mut next = indices.iter().copied();
            crate::grid::for_each_bit(known, |l| p.idx[l] = next.next().unwrap_or(0));
        }
        let largest = p.idx.iter().copied().max().unwrap_or(0);
        if usize::from(largest) >= p.values.len() {
            return None;
        }
        let mut v = Values::Palette(p);
        v.collapse();
        Some(v)
    }

    /// One value on the voxels of `known`, 0 on the others: what [`Values::from_palette`] makes
    /// of a one-value palette, without visiting the voxels one by one (most blocks of a map
    /// are free space that every ray left at the same value).
    pub(crate) fn uniform_on(v: f32, known: &Mask) -> Values {
        let known_all = known.iter().all(|&w| w == u64::MAX);
        let none_known = known.iter().all(|&w| w == 0);
        if known_all || v.to_bits() == 0f32.to_bits() {
            return Values::Uniform(v);
        }
        if none_known {
            return Values::Uniform(0.0);
        }
        // Index 0 is `v`, index 1 the 0 of the unknown voxels.
        let idx = std::array::from_fn(|l| u8::from(!mask_test(known, l)));
        Values::Palette(Box::new(Palette {
            values: vec![v, 0.0],
            idx,
        }))
    }

    /// The voxels of `known` whose value satisfies `pred`, each distinct value tested once.
    pub(crate) fn mask_where(&self, known: &Mask, pred: impl Fn(f32) -> bool) -> Mask {
        match self {
            Values::Uniform(v) => match pred(*v) {
                true => *known,
                false => EMPTY,
            },
            Values::Palette(p) => {
                let mut holds = [false; MAX_PALETTE];
                for (h, &v) in holds.iter_mut().zip(&p.values) {
                    *h = pred(v);
                }
                gather_bits(known, |l| holds[usize::from(p.idx[l])])
            }
            Values::Flat(a) => gather_bits(known, |l| pred(a[l])),
        }
    }

    /// Flat storage from the values of the voxels in `known` (in bit order); the others hold 0.
    pub(crate) fn from_known(known: &Mask, mut value: impl FnMut() -> f32) -> Values {
        let mut a = Box::new([0.0; BLOCK_VOXELS]);
        crate::grid::for_each_bit(known, |l| a[l] = value());
        Values::Flat(a)
    }

    fn palette_mut(&mut self) -> Option<&mut Palette> {
        if let Values::Uniform(v) = *self {
            *self = Values::Palette(Box::new(Palette {
                values: vec![v],
                idx: [0; BLOCK_VOXELS],
            }));
        }
        match self {
            Values::Palette(p) => Some(p),
            _ => None,
        }
    }

    fn make_flat(&mut self) {
        let flat = match self {
            Values::Uniform(v) => Box::new([*v; BLOCK_VOXELS]),
            Values::Palette(p) => p.flatten(),
            Values::Flat(_) => return,
        };
        *self = Values::Flat(flat);
    }

    /// Returns to uniform storage when every voxel holds the same value.
    fn collapse(&mut self) {
        if let Values::Palette(p) = self {
            if let Some(v) = p.single() {
                *self = Values::Uniform(v);
            }
        }
    }

    pub(crate) fn set(&mut self, l: usize, v: f32) {
        if let Values::Uniform(u) = self {
            if u.to_bits() == v.to_bits() {
                return;
            }
        }
        if let Some(p) = self.palette_mut() {
            if p.values.len() >= COMPACT_AT {
                p.compact();
            }
            if let Some(i) = p.find_or_push(v) {
                p.idx[l] = i;
                return;
            }
        }
        self.make_flat();
        if let Values::Flat(a) = self {
            a[l] = v;
        }
    }

    /// Updates the voxels of `touched` (a hit where `hits` is set, else a miss). Returns the
    /// voxels whose value changed and, among the touched ones, those whose new value satisfies
    /// `pred`.
    pub(crate) fn update(
        &mut self,
        touched: &Mask,
        hits: &Mask,
        step: Step,
        pred: impl Fn(f32) -> bool,
    ) -> (Mask, Mask) {
        if let Values::Uniform(v) = *self {
            if let Some(out) = uniform_unchanged(v, touched, hits, step, &pred) {
                return out;
            }
        }
        if let Some(p) = self.palette_mut() {
            if p.values.len() >= COMPACT_AT {
                p.compact();
            }
            if p.values.len() * 3 <= MAX_PALETTE {
                let out = update_palette(p, touched, hits, step, &pred);
                self.collapse();
                return out;
            }
        }
        self.make_flat();
        match self {
            Values::Flat(a) => update_flat(a, touched, hits, step, &pred),
            // make_flat leaves flat storage.
            _ => (EMPTY, EMPTY),
        }
    }
}

/// A uniform block whose touched voxels all keep their value (it sits at the clamp the update
/// pushes towards: free air seen again): the update's masks without making a palette and
/// collapsing it again. None when some touched voxel would change.
fn uniform_unchanged(
    v: f32,
    touched: &Mask,
    hits: &Mask,
    step: Step,
    pred: &impl Fn(f32) -> bool,
) -> Option<(Mask, Mask)> {
    let keeps = |is_hit| step.apply(v, is_hit).to_bits() == v.to_bits();
    let any_hit = (0..8).any(|w| touched[w] & hits[w] != 0);
    let any_miss = (0..8).any(|w| touched[w] & !hits[w] != 0);
    if (any_hit && !keeps(true)) || (any_miss && !keeps(false)) {
        return None;
    }
    Some((EMPTY, if pred(v) { *touched } else { EMPTY }))
}

/// Palette update: each entry's hit and miss successors are found once, then voxels only move
/// indices. The caller guarantees room for two new entries per existing one.
fn update_palette(
    p: &mut Palette,
    touched: &Mask,
    hits: &Mask,
    step: Step,
    pred: &impl Fn(f32) -> bool,
) -> (Mask, Mask) {
    let n = p.values.len();
    let (mut to_hit, mut to_miss) = ([0u8; MAX_PALETTE / 3], [0u8; MAX_PALETTE / 3]);
    for i in 0..n {
        let v = p.values[i];
        // Room is guaranteed (n * 3 <= MAX_PALETTE), so both pushes succeed.
        to_hit[i] = p.find_or_push(step.apply(v, true)).unwrap_or(0);
        to_miss[i] = p.find_or_push(step.apply(v, false)).unwrap_or(0);
    }
    let mut holds = [false; MAX_PALETTE];
    for (h, &v) in holds.iter_mut().zip(&p.values) {
        *h = pred(v);
    }
    for_each_touched(touched, hits, |l, hit| {
        let old = usize::from(p.idx[l]);
        let new = if hit { to_hit[old] } else { to_miss[old] };
        p.idx[l] = new;
        let new = usize::from(new);
        (
            p.values[new].to_bits() != p.values[old].to_bits(),
            holds[new],
        )
    })
}

fn update_flat(
    a: &mut [f32; BLOCK_VOXELS],
    touched: &Mask,
    hits: &Mask,
    step: Step,
    pred: &impl Fn(f32) -> bool,
) -> (Mask, Mask) {
    for_each_touched(touched, hits, |l, hit| {
        let v = a[l];
        let nv = step.apply(v, hit);
        a[l] = nv;
        (nv.to_bits() != v.to_bits(), pred(nv))
    })
}

/// Calls `update(voxel, hit)` for every touched voxel of a block and gathers the
/// (changed, satisfies the predicate) pair it returns into two masks.
#[inline(always)]
fn for_each_touched(
    touched: &Mask,
    hits: &Mask,
    mut update: impl FnMut(usize, bool) -> (bool, bool),
) -> (Mask, Mask) {
    let (mut changed, mut satisfied) = (EMPTY, EMPTY);
    for w in 0..8 {
        let mut bits = touched[w];
        while bits != 0 {
            let b = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            let (c, s) = update(w * 64 + b, hits[w] >> b & 1 != 0);
            changed[w] |= u64::from(c) << b;
            satisfied[w] |= u64::from(s) << b;
        }
    }
    (changed, satisfied)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::{for_each_bit, mask_count};

    /// Masks with every word kind a block has: empty, full, sparse, dense.
    fn masks() -> Vec<Mask> {
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let mut out = vec![EMPTY, [u64::MAX; 8]];
        for _ in 0..8 {
            out.push(std::array::from_fn(|w| match w % 4 {
                0 => 0,
                1 => u64::MAX,
                2 => next() & next(),
                _ => next(),
            }));
        }
        out
    }

    fn same(a: &Values, b: &Values) -> bool {
        let bits = |v: &Values| {
            (0..BLOCK_VOXELS)
                .map(|l| v.get(l).to_bits())
                .collect::<Vec<_>>()
        };
        let kind = |v: &Values| std::mem::discriminant(v);
        bits(a) == bits(b)
            && kind(a) == kind(b)
            && a.palette().map(|p| p.0) == b.palette().map(|p| p.0)
    }

    #[test]
    fn uniform_on_is_a_one_value_palette() {
        for known in masks() {
            for v in [0.0, -0.0, 0.85, -2.0] {
                let slow =
                    Values::from_palette(vec![v], &known, &[0; BLOCK_VOXELS][..mask_count(&known)])
                        .expect("index 0 fits");
                assert!(
                    same(&Values::uniform_on(v, &known), &slow),
                    "{v} on {known:x?}"
                );
            }
        }
    }

    /// Uniform blocks at either clamp, and off it, updated by every mix of touched voxels and
    /// hits: the same values, storage and masks as the same block updated as a flat array.
    #[test]
    fn a_uniform_block_at_its_clamp_updates_like_a_flat_one() {
        let step = Step {
            hit: 0.85,
            miss: -0.4,
            lo: -2.0,
            hi: 3.5,
        };
        let pred = |v: f32| v > 0.0;
        let all = masks();
        for v in [-2.0f32, 3.5, 0.0, -0.4] {
            for touched in &all {
                for hits in &all {
                    let mut fast = Values::Uniform(v);
                    let mut flat = Values::Flat(Box::new([v; BLOCK_VOXELS]));
                    let out = fast.update(touched, hits, step, pred);
                    assert_eq!(out, flat.update(touched, hits, step, pred), "{v}");
                    let bits = |x: &Values| {
                        (0..BLOCK_VOXELS)
                            .map(|l| x.get(l).to_bits())
                            .collect::<Vec<_>>()
                    };
                    assert_eq!(bits(&fast), bits(&flat), "{v}");
                    if out.0 == EMPTY {
                        assert!(matches!(fast, Values::Uniform(_)), "{v}: stays uniform");
                    }
                }
            }
        }
    }

    #[test]
    fn mask_where_tests_every_known_voxel() {
        let pred = |v: f32| v > 0.0;
        for known in masks() {
            let indices: Vec<u8> = (1..=mask_count(&known)).map(|i| (i % 4) as u8).collect();
            let palette = Values::from_palette(vec![-0.4, 0.0, 0.85, 2.0], &known, &indices)
                .expect("indices fit");
            let mut x = -1.0f32;
            let flat = Values::from_known(&known, || {
                x += 0.37;
                x
            });
            for v in [Values::Uniform(0.5), Values::Uniform(-0.5), palette, flat] {
                let mut slow = EMPTY;
                for_each_bit(&known, |l| {
                    if pred(v.get(l)) {
                        slow[l >> 6] |= 1 << (l & 63);
                    }
                });
                assert_eq!(v.mask_where(&known, pred), slow);
            }
        }
    }
}
