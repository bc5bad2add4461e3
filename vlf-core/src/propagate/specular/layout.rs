//! Where a direction's rays cross the mirrors, and the maps over those crossings.

use super::NO_SLOT;
use crate::psf::Subfield;
use crate::scene::Rgb;
use serde::{Deserialize, Serialize};

/// Where one subfield's rays cross mirrors: a compact numbering of its
/// (mirror, ray) crossings, in tile / entry / span / column order.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MirrorLayout {
    /// For each entry of [`Subfield::entries`]: its first mirror slot, or
    /// `u32::MAX` for a surface without directional maps.
    pub entry_base: Vec<u32>,
    /// Number of mirror slots.
    pub len: u32,
    /// The mirror entries as (surface, tile, entry index), sorted by surface.
    pub entries: Vec<(u32, u32, u32)>,
}

impl MirrorLayout {
    pub fn new(sub: &Subfield, has_maps: &[bool]) -> Self {
        let mut entry_base = vec![NO_SLOT; sub.entries.len()];
        let mut entries = Vec::new();
        let mut len = 0u32;
        for k in 0..sub.tile_count() {
            let first = sub.tile_start[k] as usize;
            for (local, e) in sub.tile(k).iter().enumerate() {
                if has_maps[e.surface as usize] {
                    entry_base[first + local] = len;
                    entries.push((e.surface, k as u32, (first + local) as u32));
                    len += e.rays;
                }
            }
        }
        entries.sort_by_key(|&(s, k, _)| (s, k));
        MirrorLayout {
            entry_base,
            len,
            entries,
        }
    }

    /// The tiles of `sub` that hold mirror slots, each with its range of
    /// slots: slots are numbered tile by tile, so a tile's are contiguous.
    /// This is how directional radiance is cut into per-tile blobs.
    pub fn tile_slots(&self, sub: &Subfield) -> Vec<(u32, std::ops::Range<usize>)> {
        let mut out = Vec::new();
        for k in 0..sub.tile_count() {
            let first = sub.tile_start[k] as usize;
            let mut range: Option<std::ops::Range<usize>> = None;
            for (local, e) in sub.tile(k).iter().enumerate() {
                let base = self.entry_base[first + local];
                if base != NO_SLOT {
                    let (start, end) = (base as usize, (base + e.rays) as usize);
                    range = Some(range.map_or(start..end, |r| r.start..end));
                }
            }
            if let Some(r) = range.filter(|r| !r.is_empty()) {
                out.push((k as u32, r));
            }
        }
        out
    }

    /// The mirror entries of `surface`.
    pub fn entries_of(&self, surface: u32) -> &[(u32, u32, u32)] {
        let a = self.entries.partition_point(|e| e.0 < surface);
        let b = self.entries.partition_point(|e| e.0 <= surface);
        &self.entries[a..b]
    }

    /// The mirror slot of grid cell `(x, y)` on `surface`, if its ray crosses it.
    pub fn locate(&self, sub: &Subfield, surface: u32, x: u32, y: u32) -> Option<u32> {
        let (entry, offset) = sub.locate_entry(surface, x, y)?;
        self.slot(entry, offset)
    }

    /// The mirror slot of the ray at `offset` within entry `entry` of the subfield
    /// ([`Subfield::entries`]), if the entry's surface has directional maps.
    pub fn slot(&self, entry: usize, offset: u32) -> Option<u32> {
        let base = *self.entry_base.get(entry)?;
        (base != NO_SLOT).then(|| base + offset)
    }

    /// The mirror slot of grid cell `(x, y)` on the plane of `surface`, a polygon of a mirror
    /// that may be tessellated (`plane_rep` per surface,
    /// [`crate::maps::TexelAtlas::plane_rep`]): the polygons of a mirror chart share their
    /// plane's entries, so a look-up on one reads the rays of the whole mirror.
    pub fn locate_on_plane(&self, sub: &Subfield, plane_rep: &[u32], surface: u32, x: u32, y: u32) -> Option<u32> {
        let rep = plane_rep.get(surface as usize).copied().unwrap_or(surface);
        self.locate(sub, rep, x, y)
    }
}

/// The mirror maps owned by one direction (see the module docs). Each is *held* when it has
/// one value per mirror slot of the direction, else empty, its values then as `unheld` says.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DirectionMaps {
    pub unshot: Vec<Rgb>,
    pub total: Vec<Rgb>,
    pub incident: Vec<Rgb>,
    /// What the maps not held are.
    pub unheld: Unheld,
}

impl DirectionMaps {
    /// What the next iteration shoots from, between iterations: the arrivals
    /// when they are `pending` (see [`Pending`](super::Pending)), else the unshot map.
    pub fn shooting(&self, pending: bool) -> &[Rgb] {
        if pending { &self.incident } else { &self.unshot }
    }

    /// Sets what the next iteration shoots from (see [`Self::shooting`]) and lets the other map
    /// go: the next shooting writes it afresh (the gather its unshot map, the shot its incident
    /// map, from zero), so nothing reads what it held.
    pub fn set_shooting(&mut self, pending: bool, map: Vec<Rgb>) {
        let (set, clear) = if pending {
            (&mut self.incident, &mut self.unshot)
        } else {
            (&mut self.unshot, &mut self.incident)
        };
        *set = map;
        *clear = Vec::new();
    }

    /// Bytes of the maps held.
    pub fn bytes(&self) -> usize {
        (self.unshot.capacity() + self.total.capacity() + self.incident.capacity()) * std::mem::size_of::<Rgb>()
    }
}

/// What the values of a mirror map that a process does not hold are ([`DirectionMaps`]).
///
/// A map is held — allocated, one value per slot — where the process reads or writes it, and
/// no more: every direction's in one process running the whole propagation; in the service a
/// worker's, from one snapshot to the next, those of the directions its leases shoot (their
/// shooting and total maps) and of the directions they gather from (their arrivals), and a
/// coordinator's none — at l = 8193, N = 256 the mirror scene's maps are 1.07 GB each for the
/// whole field. A map not held is empty.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Unheld {
    /// Zeros: nothing was shot into them (a new propagation, or a map that a restore cleared).
    /// Allocated when first written ([`Specular::hold_zeros`](super::Specular::hold_zeros)); read as zeros.
    #[default]
    Zero,
    /// Elsewhere: in the store, where the workers that computed them wrote them — a worker's
    /// replica between snapshots ([`crate::propagate::Propagation::restore_head`]), a coordinator whose
    /// workers shoot the maps ([`Specular::release_maps`](super::Specular::release_maps)) — or in a block that took the
    /// direction's totals along ([`crate::propagate::Propagation::compute_block`]). Reading one is an
    /// error until its batch is restored.
    Elsewhere,
}

/// One direction's subfield restricted to the mirrors with maps, with its slots laid out as the
/// whole subfield's ([`MirrorLayout`] numbers mirror slots tile by tile, entry by entry,
/// counting only mirror entries: the view has them in the same order), so every look-up of a
/// mirror's rays answers as on the whole subfield.
///
/// **All a field's mirror geometry.** The exchange (the gather of a direction's unshot map and
/// of its sources' arrivals, `Φ_in`), the cutting of mirror maps into tiles, the look-ups of a
/// walkthrough and the viewer's ray tables read the views alone; only shooting a direction reads
/// the whole subfield's numbering ([`Specular::entry_base`](super::Specular::entry_base)), and it has the subfield then.
///
/// **Built from the mirrors alone** ([`Footprints::of`](crate::psf::Footprints::of)) where the subfields are not all held:
/// a direction rasterises the mirror planes, not the scene, so no process builds every subfield
/// for its mirrors — a worker builds those of the directions it shoots, a coordinator none. It
/// is the whole subfield's mirror entries and spans, its rays numbered afresh
/// ([`Subfield::only`]), to the bit.
#[derive(Clone, Debug, PartialEq)]
pub struct MirrorView {
    pub sub: Subfield,
    pub layout: MirrorLayout,
}

impl MirrorView {
    /// The view whose subfield `sub` holds the entries of the mirrors `has_maps` marks alone.
    pub(super) fn new(sub: Subfield, has_maps: &[bool]) -> MirrorView {
        let layout = MirrorLayout::new(&sub, has_maps);
        MirrorView { sub, layout }
    }

    /// Number of mirror slots of the direction.
    pub fn slots(&self) -> usize {
        self.layout.len as usize
    }
}
