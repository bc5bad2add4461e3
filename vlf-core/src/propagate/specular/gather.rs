//! The exchange's gather: a target direction's new unshot map, read backwards from its
//! sources' arrivals (the module docs of [`super`] give the formula).

use super::{MirrorView, Pending, PowerByMirror, Route, Specular};
use crate::directions::DirectionSet;
use crate::propagate::batching::Batching;
use crate::propagate::shoot::NO_SLOT;
use crate::psf::SurfaceProjection;
use crate::scene::{Rgb, Scene};
use rayon::prelude::*;

/// Where the gather of one target direction reads ([`Specular::gather`]): per route of the
/// target, in order, every sample of the backward mapping as (the target's mirror slot, the
/// source's slot it reads, or [`NO_SLOT`] where no source ray crosses the mirror there). A
/// function of the geometry alone, the same every iteration.
///
/// Flat: the samples of every route in one array, route `r`'s at `starts[r]..starts[r + 1]`.
/// A curved mirror has millions of routes of one or two samples each (the 47 794-triangle
/// dragon at l = 2049: 4 million), where a list per route cost an allocation and 24 bytes of
/// header each, more than its samples.
#[derive(Clone, Debug)]
pub(super) struct GatherTable {
    starts: Vec<usize>,
    samples: Vec<(u32, u32)>,
}

impl GatherTable {
    /// The samples of route `r`.
    fn reads(&self, r: usize) -> &[(u32, u32)] {
        &self.samples[self.starts[r]..self.starts[r + 1]]
    }
}

impl Specular {
    /// The backward mapping of target direction `i` ([`GatherTable`]), for the routes `wanted`
    /// (the others' ranges left empty): every slot of the route's mirror in `i` reads the source
    /// ray through the same point of the mirror.
    fn gather_table(&self, scene: &Scene, i: usize, wanted: impl Fn(&Route) -> bool) -> GatherTable {
        let MirrorView { sub, layout } = &self.views[i];
        let n = sub.grid.resolution;
        // The target's rays on the last route's mirror: routes come by mirror, each mirror's
        // several sources read through the same points, so it is found once per mirror.
        let mut on_mirror: Option<(u32, SurfaceProjection)> = None;
        let mut table = GatherTable {
            starts: Vec::with_capacity(self.routes[i].len() + 1),
            samples: Vec::new(),
        };
        table.starts.push(0);
        for route in &self.routes[i] {
            if wanted(route) {
                let proj = match &on_mirror {
                    Some((m, proj)) if *m == route.mirror => proj,
                    _ => {
                        let surface = &scene.surfaces[route.mirror as usize];
                        let proj = SurfaceProjection::new(&sub.frame, n, surface.normal, surface.offset);
                        &on_mirror.insert((route.mirror, proj)).1
                    }
                };
                let MirrorView {
                    sub: source,
                    layout: source_layout,
                } = &self.views[route.source as usize];
                for &(_, k, e) in layout.entries_of(route.mirror) {
                    let base = layout.entry_base[e as usize];
                    let entry = &sub.entries[e as usize];
                    sub.rays_of(k as usize, entry, |slot, x, y| {
                        let p = proj.point_at(x as f64 + 0.5, y as f64 + 0.5);
                        let g = source.frame.to_grid(p, n);
                        let read = if g.x >= 0.0 && g.y >= 0.0 {
                            source_layout.locate(source, route.mirror, g.x as u32, g.y as u32)
                        } else {
                            None
                        };
                        (table.samples).push((base + slot - entry.first_ray, read.unwrap_or(NO_SLOT)));
                    });
                }
            }
            table.starts.push(table.samples.len());
        }
        table
    }

    /// Turns the pending `Φ_in` around by mirror now and keeps it, for the gathers that this
    /// process runs next from the same [`Pending`]: a process running the whole propagation.
    pub(crate) fn prepare_gathers(&self) {
        if let Some(pending) = &self.pending {
            self.by_mirror(pending);
        }
    }

    /// `pending`'s known `Φ_in` by mirror ([`PowerByMirror`]), turned around once per what is
    /// known.
    fn by_mirror<'a>(&self, pending: &'a Pending) -> &'a PowerByMirror {
        (pending.by_mirror).get_or_init(|| Box::new(PowerByMirror::new(&pending.power_in, self.mirrors.len())))
    }

    /// `Φ_in` of `route`'s mirror along its source.
    fn route_power(&self, lit: &PowerByMirror, route: &Route) -> Rgb {
        lit.power(self.ordinal[route.mirror as usize], route.source)
    }

    /// The batches of source directions whose arrivals the gather of `targets` reads (those of
    /// the routes into them that carry power), increasing: what a worker reads from the store
    /// before it gathers a block. As the batches that shot the arrivals settled them
    /// ([`Settled::sources`](super::Settled::sources)); arrivals not settled yet read every batch.
    pub fn source_batches(
        &self,
        targets: std::ops::Range<usize>,
        pending: &Pending,
        batching: &Batching,
    ) -> Vec<usize> {
        let Some(settled) = &pending.settled else {
            return (0..batching.count()).collect();
        };
        let mut found = vec![false; batching.count()];
        if !targets.is_empty() {
            for t in batching.batch_of(targets.start)..=batching.batch_of(targets.end - 1) {
                for &b in settled.sources.get(t).map_or(&[][..], Vec::as_slice) {
                    if let Some(f) = found.get_mut(b as usize) {
                        *f = true;
                    }
                }
            }
        }
        (0..found.len()).filter(|&b| found[b]).collect()
    }

    /// Refuses to gather `targets` unless the `Φ_in` of every source it reads is known here
    /// ([`Specular::know_arrivals`]): a source not known reads as dark, so a replica that did
    /// not restore a batch it gathers from would gather too little, without a word.
    pub fn check_sources_known(
        &self,
        targets: std::ops::Range<usize>,
        pending: &Pending,
        batching: &Batching,
    ) -> crate::Result<()> {
        for b in self.source_batches(targets, pending, batching) {
            if let Some(d) = batching.range(b).find(|&d| pending.power_in(d).is_none()) {
                return Err(crate::Error::Parameter(format!(
                    "the mirror arrival map of direction {d} (batch {b}) is not restored"
                )));
            }
        }
        Ok(())
    }

    /// Reflects the pending arrivals (the incident maps) of every direction
    /// into new unshot maps and clears the incident maps: the exchange, as
    /// one process does it at the start of the iteration that shoots them.
    /// Nothing happens when no arrivals are pending.
    ///
    /// In place: each direction's stale unshot map (while arrivals are pending, nothing reads
    /// it) is cleared and gathered into, and the arrival maps, once every gather has read them,
    /// are cleared to be the next incident maps. Two maps of fresh memory per slot every
    /// iteration were a third of the mirror dragon's gathering on the 2-core VM, most of it the
    /// system zeroing pages.
    pub fn gather_all(&mut self, scene: &Scene, directions: &DirectionSet) {
        if self.pending.is_none() {
            return;
        }
        self.hold_zeros(0..directions.len());
        debug_assert!(
            self.holds_all(),
            "one process gathers only where every arrival map is here"
        );
        // Every arrival map is here: `Φ_in` not known yet (a propagation that finished the
        // iteration from blocks it adopted, say) is found from them, never read as dark.
        let l = directions.len();
        if (self.pending.as_ref()).is_some_and(|p| (0..l).any(|d| p.power_in(d).is_none())) {
            self.know_arrivals(directions, 0..l);
        }
        let Some(pending) = self.pending.take() else {
            return;
        };
        let incident: Vec<Vec<Rgb>> = (self.maps.iter_mut())
            .map(|m| std::mem::take(&mut m.incident))
            .collect();
        let mut unshot: Vec<Vec<Rgb>> = (self.maps.iter_mut()).map(|m| std::mem::take(&mut m.unshot)).collect();
        let read = |d: usize| incident[d].as_slice();
        let this = &*self;
        (unshot.par_iter_mut().enumerate()).for_each(|(i, out)| {
            (this.gather_into(scene, directions, &read, &pending, i, out))
                .expect("one process holds every direction's arrivals")
        });
        let cleared: Vec<Vec<Rgb>> = (incident.into_par_iter())
            .map(|mut map| {
                map.fill([0.0; 3]);
                map
            })
            .collect();
        for ((maps, unshot), incident) in self.maps.iter_mut().zip(unshot).zip(cleared) {
            maps.unshot = unshot;
            maps.incident = incident;
        }
    }

    /// The new unshot map of target direction `i` from the pending arrivals
    /// `incident(source)` of its routes' sources and their `Φ_in` as this process knows it
    /// ([`Specular::know_arrivals`]; see the module docs): what a worker computes for the
    /// directions it shoots. A source whose `Φ_in` is not known here reads as dark: ask
    /// [`Specular::check_sources_known`] first. An arrival map it reads whose `Φ_in` is known
    /// but that is not held is an error, not zeros.
    pub fn gather<'a>(
        &self,
        scene: &Scene,
        directions: &DirectionSet,
        incident: &(dyn Fn(usize) -> &'a [Rgb] + Sync),
        pending: &Pending,
        i: usize,
    ) -> crate::Result<Vec<Rgb>> {
        let mut out = Vec::new();
        self.gather_into(scene, directions, incident, pending, i, &mut out)?;
        Ok(out)
    }

    /// [`Specular::gather`] into `out`, whatever it held: cleared to the direction's zeros
    /// first, its memory kept where it has room.
    pub fn gather_into<'a>(
        &self,
        scene: &Scene,
        directions: &DirectionSet,
        incident: &(dyn Fn(usize) -> &'a [Rgb] + Sync),
        pending: &Pending,
        i: usize,
        out: &mut Vec<Rgb>,
    ) -> crate::Result<()> {
        let power = self.by_mirror(pending);
        let lit = |route: &Route| !self.route_power(power, route).iter().all(|&p| p <= 0.0);
        // Backward mapping: every slot of P in i reads the incident radiance of the source ray
        // through the same point of P. Found once per direction where tables are kept (a
        // fifth of the mirror scene's in-process run went to finding it again every
        // iteration), else for the routes that carry power this time.
        let found;
        let table = if self.keep_gather_tables {
            self.gather_tables[i].get_or_init(|| self.gather_table(scene, i, |_| true))
        } else {
            found = self.gather_table(scene, i, lit);
            &found
        };
        let weight_i = directions.get(i).weight;
        let len = self.views[i].layout.len as usize;
        if out.capacity() >= len {
            out.clear();
            out.resize(len, [0.0; 3]);
        } else {
            // Zeroed by the allocator, which memory fresh from the system is already.
            *out = vec![[0.0; 3]; len];
        }
        let mut samples: Vec<(u32, Rgb)> = Vec::new();
        for (r, route) in self.routes[i].iter().enumerate() {
            let pin = self.route_power(power, route);
            if pin.iter().all(|&p| p <= 0.0) {
                continue;
            }
            let reads = table.reads(r);
            if reads.is_empty() {
                // The mirror has no slot in the target: nothing to fill, nothing to read.
                continue;
            }
            let rho = scene.materials[scene.surfaces[route.mirror as usize].material].specular;
            let source_incident = incident(route.source as usize);
            if !self.holds(route.source as usize, source_incident) {
                return Err(crate::Error::Parameter(format!(
                    "the mirror arrival map of direction {} is not restored",
                    route.source
                )));
            }
            samples.clear();
            samples.extend(reads.iter().map(|&(slot, read)| {
                let v = if read == NO_SLOT {
                    [0.0; 3]
                } else {
                    source_incident[read as usize]
                };
                (slot, v)
            }));
            // Scale so the route carries exactly b·ρs·Φ_in (per channel);
            // where backward mapping found nothing lit (a lit area far smaller
            // than a ray cell), spread the power evenly instead.
            for c in 0..3 {
                let target = route.weight * rho[c] * pin[c];
                if target <= 0.0 {
                    continue;
                }
                let sum: f64 = samples.iter().map(|(_, v)| v[c]).sum();
                if sum > 0.0 {
                    let k = target / (sum * weight_i);
                    for (slot, v) in &samples {
                        out[*slot as usize][c] += v[c] * k;
                    }
                } else {
                    let each = target / (samples.len() as f64 * weight_i);
                    for (slot, _) in &samples {
                        out[*slot as usize][c] += each;
                    }
                }
            }
        }
        Ok(())
    }
}
