//! The mirror geometry: what a propagation's specular set-up computes over every direction — each
//! direction's mirror view and every target's reflection routes ([`Specular::new`]) — kept with a
//! job, so that the coordinator computes it once and nobody computes it again.
//!
//! A curved mirror makes it the longest part of a worker's set-up: for the mirror dragon (47 794
//! mirror triangles) at l = 2049, N = 128, rasterising the mirror planes in every direction and
//! finding their 4 million routes took 6 s of one thread on the 2-core VM, and every worker did
//! it again after the coordinator had, before it could shoot. Stored, it is 168 MB of tables,
//! 34 MB once compressed, and a worker reads and checks it in under a second.
//!
//! It is a pure function of the scene, the options and the mirrors light reaches (which the
//! [`super::Survey`] says), so a propagation that reads it ([`super::Propagation::with_stored`])
//! has the bits of one that computes it. What it was computed for is written with it
//! ([`Surveyed`]) and checked, with every table, before anything indexes with it
//! ([`MirrorGeometry::check`]): a geometry of another job, of another layout or garbage is an
//! error, never a field. It is the output of [`Specular::new`] for its version: a change to how
//! views or routes are found changes the field's bits, and bumps `VERSION` with it, so that a
//! job's stored geometry is never read by a build that would have found another.

use super::Options;
use super::checkpoint::encode;
use super::specular::{Route, Specular};
use super::survey::{Surveyed, read_versioned, read_versioned_from};
use crate::psf::{Subfield, Subfields};
use crate::scene::Scene;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// The version a [`MirrorGeometry`]'s bytes start with: of the layout, and of how
/// [`Specular::new`] finds views and routes (see the module docs).
const VERSION: u32 = 1;

/// A specular state's views and routes, as a job stores them: see the module docs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MirrorGeometry {
    version: u32,
    /// What it was computed for.
    pub of: Surveyed,
    /// The mirrors with maps, by increasing surface number ([`Specular::mirrors`]).
    pub mirrors: Vec<u32>,
    /// Per direction, the subfield of its view ([`super::specular::MirrorView`]): its mirror
    /// entries alone. The layout is found from it again, one pass over its entries.
    pub views: Vec<Subfield>,
    /// Per target direction, what feeds it ([`Specular::routes`]).
    pub routes: Vec<Vec<Route>>,
}

/// [`MirrorGeometry`] borrowed from a [`Specular`], written without copying a table: the same
/// fields in the same order, so the bytes read back as one. What a job stores
/// ([`super::Propagation::mirror_geometry_ref`]): serialised into a compressor as it goes
/// ([`MirrorGeometryRef::write_to`]), as a worker reads it out of one
/// ([`MirrorGeometry::read_from`]), since a buffer of the whole was 168 MB of fresh memory
/// for the mirror dragon at l = 2049, N = 128.
#[derive(Serialize)]
pub struct MirrorGeometryRef<'a> {
    version: u32,
    of: Surveyed,
    mirrors: &'a [u32],
    views: Vec<&'a Subfield>,
    routes: &'a [Vec<Route>],
}

impl MirrorGeometryRef<'_> {
    /// Length of the bytes [`MirrorGeometryRef::write_to`] writes.
    pub fn serialized_len(&self) -> u64 {
        bincode::serialized_size(self).expect("bincode sizes plain numbers")
    }

    /// Writes the bytes of the geometry, those [`MirrorGeometry::to_bytes`] makes of it.
    pub fn write_to(&self, writer: impl std::io::Write) -> std::io::Result<()> {
        super::checkpoint::encode_into(writer, self)
    }

    /// The bytes of the geometry, for [`MirrorGeometry::from_bytes`].
    pub fn to_bytes(&self) -> Vec<u8> {
        encode(self)
    }
}

impl MirrorGeometry {
    /// The bytes of this geometry, for [`MirrorGeometry::from_bytes`].
    pub fn to_bytes(&self) -> Vec<u8> {
        encode(self)
    }

    /// `specular`'s geometry, computed for `scene` with `options`, borrowed: that of the
    /// [`MirrorGeometry`] it is, not copied into one.
    pub(crate) fn borrowed<'a>(scene: &Scene, options: &Options, specular: &'a Specular) -> MirrorGeometryRef<'a> {
        let (mirrors, views, routes) = specular.geometry();
        MirrorGeometryRef {
            version: VERSION,
            of: Surveyed::of(scene, options),
            mirrors,
            views,
            routes,
        }
    }

    /// Reads a geometry; what cannot be one (truncated, another version, trailing bytes) is a
    /// [`crate::Error::Decode`]. Whether it fits a scene is [`MirrorGeometry::check`]'s to say.
    pub fn from_bytes(bytes: &[u8]) -> crate::Result<MirrorGeometry> {
        read_versioned(bytes, VERSION, "mirror geometry")
    }

    /// [`MirrorGeometry::from_bytes`] out of `reader`, which holds at most `len` bytes, as they
    /// come: reads no further than the geometry (whether anything follows is the caller's to
    /// check), and refuses a length in the bytes that claims more than `len` before allocating
    /// for it.
    pub fn read_from(reader: impl std::io::Read, len: u64) -> crate::Result<MirrorGeometry> {
        read_versioned_from(reader, len, VERSION, "mirror geometry")
    }

    /// Whether this can be the geometry of `mirrors` in `scene` with `options`, over the
    /// directions and grid of `subfields`: computed for them ([`Surveyed`]), of these mirrors,
    /// one view per direction in its frame whose tables hold these mirrors alone
    /// ([`Subfield::check_tables`]), and per direction routes from these mirrors and existing
    /// sources, each (mirror, source) once and in order, with a share in (0, 1]. A geometry that
    /// passes indexes nothing out of bounds; one that does not is refused with what is wrong.
    pub fn check(&self, scene: &Scene, options: &Options, subfields: &Subfields, mirrors: &[u32]) -> crate::Result<()> {
        let misfit = |m: String| Err(crate::Error::Decode(format!("the mirror geometry {m}")));
        let here = Surveyed::of(scene, options);
        if self.of != here {
            return misfit(if self.of.scene_hash != here.scene_hash {
                "was computed for another scene".into()
            } else {
                format!(
                    "was computed for l = {}, {:?}, texels of {} cells (this job: l = {}, {:?}, {} cells)",
                    self.of.directions, self.of.grid, self.of.texel_cells, here.directions, here.grid, here.texel_cells
                )
            });
        }
        let mut expected = mirrors.to_vec();
        expected.sort_unstable();
        expected.dedup();
        if expected.is_empty() {
            return misfit("is of a job whose survey maps no mirror".into());
        }
        if self.mirrors != expected {
            return misfit(format!(
                "is of other mirrors ({}) than the survey maps ({})",
                self.mirrors.len(),
                expected.len()
            ));
        }
        let is_mirror = |s: u32| self.mirrors.binary_search(&s).is_ok();
        check_views(&self.views, subfields, is_mirror).or_else(misfit)?;
        let l = subfields.len();
        if self.routes.len() != l {
            return misfit(format!("has {} route lists for {l} directions", self.routes.len()));
        }
        // Direction by direction on every thread; the first misfit in direction order is told,
        // whichever thread finds it first, so the message is the same every time.
        let misfit_routes = |(target, routes): (usize, &Vec<Route>)| {
            for route in routes {
                if !is_mirror(route.mirror) || route.source as usize >= l {
                    return Some(format!(
                        "routes direction {target} from mirror {} and direction {}, not one of the job's",
                        route.mirror, route.source
                    ));
                }
                if !(route.weight > 0.0 && route.weight <= 1.0) {
                    return Some(format!("gives direction {target} a route of share {}", route.weight));
                }
            }
            let ordered = (routes.windows(2)).all(|w| (w[0].mirror, w[0].source) < (w[1].mirror, w[1].source));
            (!ordered).then(|| format!("lists the routes of direction {target} out of order or twice"))
        };
        if let Some(m) = self.routes.par_iter().enumerate().find_map_first(misfit_routes) {
            return misfit(m);
        }
        Ok(())
    }

    /// The specular state of `mirrors` this geometry is, once [`MirrorGeometry::check`] finds it
    /// fits: the state [`Specular::new`] builds, to the bit.
    pub fn into_specular(
        self,
        scene: &Scene,
        options: &Options,
        subfields: &Subfields,
        mirrors: &[u32],
    ) -> crate::Result<Specular> {
        self.check(scene, options, subfields, mirrors)?;
        Ok(Specular::from_geometry(scene, self))
    }
}

/// Whether `views` can be the mirror views of the directions of `subfields`: one per direction,
/// each in its direction's frame and grid, with tables that index nothing out of bounds
/// ([`Subfield::check_tables`]) and hold only surfaces that `holds` accepts. Says what is wrong
/// if not.
pub(super) fn check_views(
    views: &[Subfield],
    subfields: &Subfields,
    holds: impl Fn(u32) -> bool + Sync,
) -> Result<(), String> {
    let l = subfields.len();
    if views.len() != l {
        return Err(format!("has {} views for {l} directions", views.len()));
    }
    // On every thread, the first misfit in direction order told (see `MirrorGeometry::check`).
    let misfit = |(d, view): (usize, &Subfield)| {
        if view.frame != subfields.frame(d) || view.grid != subfields.grid() {
            return Some(format!("has the view of another frame or grid for direction {d}"));
        }
        (view.check_tables(&holds))
            .err()
            .map(|m| format!("has a view of direction {d} that {m}"))
    };
    views.par_iter().enumerate().find_map_first(misfit).map_or(Ok(()), Err)
}

/// [`Specular::from_mirror_planes`], once `planes` are found to be the mirror planes of the
/// directions of `subfields` ([`check_views`]: surfaces of `scene` that are mirrors alone).
pub(super) fn specular_from_planes(
    scene: &Scene,
    directions: &crate::directions::DirectionSet,
    subfields: &Subfields,
    planes: Vec<Subfield>,
    mirrors: Vec<u32>,
) -> crate::Result<Specular> {
    let surfaces = scene.surfaces.len();
    let is_mirror = |s: u32| (s as usize) < surfaces && scene.material(s as usize).is_mirror();
    check_views(&planes, subfields, is_mirror)
        .map_err(|m| crate::Error::Decode(format!("the survey's mirror planes: it {m}")))?;
    Ok(Specular::from_mirror_planes(scene, directions, planes, mirrors))
}
