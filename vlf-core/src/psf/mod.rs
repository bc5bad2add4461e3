//! Parallel subfields (PSF): for one direction, an `N × N` grid of parallel
//! rays over the scene, cut into `m × m` tiles.
//!
//! Ray `(i, j)` of the subfield of direction `w` starts on the plane through
//! the origin perpendicular to `w`, at `x·u + y·v` with
//! `x = (2i + 1)/N − 1`, `y = (2j + 1)/N − 1` (the paper's equation 1), and
//! travels along `+w` (light also travels along `−w` on the same line). As the
//! scene lies in the unit sphere, the grid covers it for every direction.
//!
//! Each tile lists the surfaces its rays cross, and for each surface a
//! *visibility map* stored as an **edge table**: spans of covered rays per
//! tile row (one for a convex surface; coplanar neighbours of a chart share
//! their representative's entry, see [`Subfield::build`] and [`footprint`]). The depth of a
//! surface along a ray and the texel it crosses are not stored: they are
//! affine in the ray's grid coordinates and recomputed on the fly
//! ([`SurfaceProjection`]), as in the paper.

pub mod footprint;
pub mod raster;
pub mod subfields;

pub use footprint::{Footprints, RasterScratch};
pub use subfields::{SubfieldMemory, SubfieldRef, Subfields};

use glam::{DVec2, DVec3};
use serde::{Deserialize, Serialize};

/// The orthonormal frame of a subfield: rays travel along `w`; `u`, `v` span
/// the grid plane, built deterministically from `w` alone; the lattice of rays
/// sits on that plane at the phase `shift`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PsfFrame {
    pub u: DVec3,
    pub v: DVec3,
    pub w: DVec3,
    /// Offset of the ray lattice from the grid of the paper's equation 1, in ray spacings, in
    /// `[−½, ½)²`: ray `(i, j)` starts at `x = (2i + 1 + 2·shift.x)/N − 1` (and `y` alike).
    ///
    /// Why: the rays that cross a polygon are its area as the field sees it (its discrete
    /// area, see [`crate::propagate`]), and on a lattice at a fixed phase that count errs the
    /// same way in every direction whose lattice lines up with the polygon's edges — an
    /// axis-aligned lamp on the near-axis lattices, where it errs by up to a row of rays. The
    /// errors then add up over the directions into a bias (a lamp of 6.4 ray spacings read
    /// 2.4 % too large over 513 directions). A lattice at its own phase per direction
    /// ([`crate::directions::DirectionSet::frame`]) turns that into errors of both signs
    /// that average out: the count is an unbiased estimate of the projected area when the
    /// phase is uniform.
    #[serde(default)]
    pub shift: DVec2,
}

impl PsfFrame {
    pub fn new(w: DVec3) -> Self {
        let w = w.normalize();
        // The world axis least aligned with w gives a well-conditioned cross product.
        let a = if w.x.abs() <= w.y.abs() && w.x.abs() <= w.z.abs() {
            DVec3::X
        } else if w.y.abs() <= w.z.abs() {
            DVec3::Y
        } else {
            DVec3::Z
        };
        let u = a.cross(w).normalize();
        let v = w.cross(u);
        PsfFrame {
            u,
            v,
            w,
            shift: DVec2::ZERO,
        }
    }

    /// The frame of [`PsfFrame::new`] with its ray lattice at phase `shift` (ray spacings).
    pub fn with_shift(w: DVec3, shift: DVec2) -> Self {
        PsfFrame { shift, ..Self::new(w) }
    }

    /// Where the ray through grid coordinates `(x, y)` (cell centres at `i + ½`) starts, on the
    /// plane through the origin perpendicular to `w`, for an `n × n` grid.
    pub fn ray_origin(&self, x: f64, y: f64, n: u32) -> DVec3 {
        let step = 2.0 / n as f64;
        -self.u - self.v + self.u * ((x + self.shift.x) * step) + self.v * ((y + self.shift.y) * step)
    }

    /// Projects a VLF-frame point into grid units of an `n × n` grid.
    pub fn to_grid(&self, p: DVec3, n: u32) -> DVec2 {
        let half = n as f64 * 0.5;
        DVec2::new((p.dot(self.u) + 1.0) * half, (p.dot(self.v) + 1.0) * half) - self.shift
    }
}

/// Size of the ray grids: `N` rays per side, tiles of `m × m` rays.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct GridSize {
    pub resolution: u32,
    pub tile: u32,
}

impl GridSize {
    /// Largest accepted resolution: beyond it one subfield alone holds more
    /// rays than any scene of this method needs, and memory explodes.
    pub const MAX_RESOLUTION: u32 = 4096;

    pub fn new(resolution: u32, tile: u32) -> crate::Result<Self> {
        if !(2..=Self::MAX_RESOLUTION).contains(&resolution) {
            return Err(crate::Error::Parameter(format!(
                "resolution N = {resolution} is out of range 2..={}",
                Self::MAX_RESOLUTION
            )));
        }
        if tile == 0 || tile > resolution || !resolution.is_multiple_of(tile) {
            return Err(crate::Error::Parameter(format!(
                "tile size m = {tile} must divide the resolution N = {resolution}"
            )));
        }
        Ok(GridSize { resolution, tile })
    }

    /// Tiles per side, `n = N / m`.
    pub fn tiles_per_side(&self) -> u32 {
        self.resolution / self.tile
    }

    /// Distance between neighbouring rays in the VLF frame: `2 / N`.
    pub fn ray_spacing(&self) -> f64 {
        2.0 / self.resolution as f64
    }

    /// Cross-section of one ray's beam in the VLF frame.
    pub fn cell_area(&self) -> f64 {
        self.ray_spacing() * self.ray_spacing()
    }
}

/// A run of covered rays in one row of a tile, in tile-local coordinates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Span {
    pub row: u16,
    pub start: u16,
    pub end: u16,
}

/// A subfield's tiles in the making ([`Subfield::build_with`]): kept by the caller's
/// [`RasterScratch`] from one direction to the next, so that building one allocates its tables
/// and little else (a cursor per tile).
#[derive(Default)]
pub(crate) struct TileScratch {
    /// (tile, representative surface, span) as rasterised.
    pieces: Vec<(u32, u32, Span)>,
    /// (surface, span) grouped by tile.
    by_tile: Vec<(u32, Span)>,
    /// Where each tile's group starts in `by_tile`, and its end.
    first: Vec<u32>,
    entries: Vec<TileSurface>,
    spans: Vec<Span>,
}

/// One surface in a tile: its id and its edge table (spans `first..first+count`
/// of [`Subfield::spans`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TileSurface {
    pub surface: u32,
    pub first_span: u32,
    pub span_count: u32,
    /// Number of rays of the tile that cross the surface.
    pub rays: u32,
    /// Index of this entry's first ray among all (surface, ray) crossings of
    /// the subfield, in tile / entry / span / column order: per-ray maps of a
    /// subfield (radiance maps) are flat arrays indexed by these *slots*.
    pub first_ray: u32,
}

/// The subfield of one direction, its tiles in compressed-row form: tile `k`
/// (row-major, `k = t·n + s`) owns `entries[tile_start[k]..tile_start[k+1]]`,
/// sorted by surface id.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Subfield {
    pub frame: PsfFrame,
    pub grid: GridSize,
    pub tile_start: Vec<u32>,
    pub entries: Vec<TileSurface>,
    pub spans: Vec<Span>,
}

impl Subfield {
    /// Rasterises every surface of the scene, prepared as `footprints`, into the subfield whose
    /// rays run along `frame.w` at the lattice phase `frame.shift`.
    ///
    /// Coplanar neighbours of one diffuse chart are the same hit for a ray, so they share one
    /// entry, their representative's ([`crate::maps::TexelAtlas::plane_rep`]), rasterised by
    /// the group's outline ([`footprint`]): a wall cut into 3 200 triangles then costs a tile
    /// one entry and a direction one outline, as a plain quad does. (An entry's row may hold
    /// several spans, where a chart is not convex.)
    pub fn build(footprints: &Footprints, frame: PsfFrame, grid: GridSize) -> Self {
        Self::build_with(footprints, frame, grid, &mut RasterScratch::default())
    }

    /// [`Subfield::build`] with the caller's working memory.
    pub fn build_with(footprints: &Footprints, frame: PsfFrame, grid: GridSize, scratch: &mut RasterScratch) -> Self {
        let n = grid.resolution;
        let m = grid.tile;
        let per_side = grid.tiles_per_side() as usize;
        let tiles = per_side * per_side;
        // Every covered run of a row cut at the tiles' edges, as it comes: (tile, representative
        // surface, span in tile-local coordinates).
        let mut pieces = std::mem::take(&mut scratch.tiles.pieces);
        pieces.clear();
        footprints.rasterize(&frame, n, scratch, |rep, s| {
            let tile_row = s.row / m;
            let local_row = (s.row % m) as u16;
            let mut x = s.start;
            while x < s.end {
                let tile_col = x / m;
                let tile_end = ((tile_col + 1) * m).min(s.end);
                pieces.push((
                    tile_row * per_side as u32 + tile_col,
                    rep,
                    Span {
                        row: local_row,
                        start: (x - tile_col * m) as u16,
                        end: (tile_end - tile_col * m) as u16,
                    },
                ));
                x = tile_end;
            }
        });
        let TileScratch {
            pieces: kept,
            by_tile,
            first,
            entries,
            spans,
        } = &mut scratch.tiles;
        // Grouped by tile (a counting sort): `first[t]..first[t + 1]` of `by_tile`.
        first.clear();
        first.resize(tiles + 1, 0);
        for &(tile, _, _) in &pieces {
            first[tile as usize + 1] += 1;
        }
        for t in 0..tiles {
            first[t + 1] += first[t];
        }
        by_tile.clear();
        by_tile.resize(
            pieces.len(),
            (
                0,
                Span {
                    row: 0,
                    start: 0,
                    end: 0,
                },
            ),
        );
        let mut at: Vec<u32> = first[..tiles].to_vec();
        for &(tile, surface, span) in &pieces {
            by_tile[at[tile as usize] as usize] = (surface, span);
            at[tile as usize] += 1;
        }
        *kept = pieces;
        let mut tile_start = Vec::with_capacity(tiles + 1);
        entries.clear();
        spans.clear();
        let mut slots = 0u32;
        for t in 0..tiles {
            tile_start.push(entries.len() as u32);
            let bucket = &mut by_tile[first[t] as usize..first[t + 1] as usize];
            // By surface, then row and start: a representative's spans together, in order (no
            // two pieces share all three, so the order they came in does not matter).
            bucket.sort_unstable_by_key(|&(surface, s)| (surface, s.row, s.start));
            let mut k = 0;
            while k < bucket.len() {
                let surface = bucket[k].0;
                let first_span = spans.len() as u32;
                let mut rays = 0u32;
                while k < bucket.len() && bucket[k].0 == surface {
                    let s = bucket[k].1;
                    rays += (s.end - s.start) as u32;
                    let joins = spans.len() as u32 > first_span
                        && spans
                            .last()
                            .is_some_and(|last| last.row == s.row && last.end == s.start);
                    match spans.last_mut() {
                        Some(last) if joins => last.end = s.end,
                        _ => spans.push(s),
                    }
                    k += 1;
                }
                entries.push(TileSurface {
                    surface,
                    first_span,
                    span_count: spans.len() as u32 - first_span,
                    rays,
                    first_ray: slots,
                });
                slots += rays;
            }
        }
        tile_start.push(entries.len() as u32);
        // Copied out at their size: held (all of a field's, or a rotated copy's kept from its
        // areas to its shot), tables grown by doubling keep up to half again of slack, which
        // `shrink_to_fit` does not give back where the allocator shrinks in place (mimalloc
        // keeps a block that is still half used). Built in the scratch's, a direction allocates
        // little else: the dragon's `vlf run` peaks at 565 MB rather than 740–760 MB.
        Subfield {
            frame,
            grid,
            tile_start,
            entries: entries.clone(),
            spans: spans.clone(),
        }
    }

    /// Whether these tables are a subfield's, for one read from elsewhere (a job's stored mirror
    /// geometry) before anything indexes with them: one entry list per tile of the grid, each
    /// tile's surfaces increasing and each one that `surface` accepts, every entry's spans within
    /// the table and the tile, its rays their length and its first slot the count before it. The
    /// look-ups then stay in bounds; what the tables say of the scene is the caller's to check.
    pub fn check_tables(&self, surface: impl Fn(u32) -> bool) -> Result<(), String> {
        let (m, tiles) = (self.grid.tile, self.grid.tiles_per_side() as usize);
        if self.tile_start.len() != tiles * tiles + 1 || self.tile_start.first() != Some(&0) {
            return Err(format!(
                "has {} tile starts for {} tiles",
                self.tile_start.len(),
                tiles * tiles
            ));
        }
        if !self.tile_start.is_sorted() {
            return Err("has tile starts out of order".into());
        }
        if self.tile_start.last().map(|&end| end as usize) != Some(self.entries.len()) {
            return Err("has tile starts that do not end at its entries' count".into());
        }
        let mut slots = 0u32;
        for k in 0..self.tile_count() {
            let entries = self.tile(k);
            if !entries.windows(2).all(|w| w[0].surface < w[1].surface) {
                return Err(format!("lists the surfaces of tile {k} out of order or twice"));
            }
            for e in entries {
                if !surface(e.surface) {
                    return Err(format!("has an entry of surface {}, which it cannot hold", e.surface));
                }
                let spans = (e.first_span.checked_add(e.span_count))
                    .and_then(|end| self.spans.get(e.first_span as usize..end as usize))
                    .ok_or_else(|| format!("has spans of tile {k} past its {} spans", self.spans.len()))?;
                let mut rays = 0u64;
                for s in spans {
                    if !(u32::from(s.row) < m && s.start < s.end && u32::from(s.end) <= m) {
                        return Err(format!("has a span {s:?} outside its {m}-ray tile {k}"));
                    }
                    rays += u64::from(s.end - s.start);
                }
                if u64::from(e.rays) != rays || e.first_ray != slots {
                    return Err(format!("miscounts the rays of tile {k}"));
                }
                slots = slots
                    .checked_add(e.rays)
                    .ok_or_else(|| "has more rays than slots can number".to_string())?;
            }
        }
        Ok(())
    }

    /// The surfaces of tile `k` with their edge tables.
    pub fn tile(&self, k: usize) -> &[TileSurface] {
        &self.entries[self.tile_start[k] as usize..self.tile_start[k + 1] as usize]
    }

    pub fn tile_count(&self) -> usize {
        self.tile_start.len() - 1
    }

    pub fn spans_of(&self, entry: &TileSurface) -> &[Span] {
        &self.spans[entry.first_span as usize..(entry.first_span + entry.span_count) as usize]
    }

    /// Total number of (surface, ray) crossings: the length of a per-ray map.
    pub fn slot_count(&self) -> usize {
        self.entries.last().map_or(0, |e| (e.first_ray + e.rays) as usize)
    }

    /// The slot of the ray through grid cell `(x, y)` on `surface`, if that
    /// ray crosses it. Constant time but for finding the surface in the
    /// tile's short sorted list ([`find_surface`]) — the paper's only search.
    pub fn locate(&self, surface: u32, x: u32, y: u32) -> Option<u32> {
        self.locate_entry(surface, x, y)
            .map(|(e, offset)| self.entries[e].first_ray + offset)
    }

    /// Like [`Subfield::locate`], but returns the tile entry's index in
    /// [`Subfield::entries`] and the ray's offset within the entry.
    pub fn locate_entry(&self, surface: u32, x: u32, y: u32) -> Option<(usize, u32)> {
        let (m, n) = (self.grid.tile, self.grid.resolution);
        if x >= n || y >= n {
            return None;
        }
        let k = ((y / m) * self.grid.tiles_per_side() + x / m) as usize;
        let entries = self.tile(k);
        let local = find_surface(entries, surface)?;
        let offset = self.offset_in(&entries[local], (y % m) as u16, (x % m) as u16)?;
        Some((self.tile_start[k] as usize + local, offset))
    }

    /// The offset within `entry` of the ray at tile-local `(row, col)`, if the entry covers it.
    fn offset_in(&self, entry: &TileSurface, row: u16, col: u16) -> Option<u32> {
        let mut offset = 0u32;
        for s in self.spans_of(entry) {
            if s.row == row && s.start <= col && col < s.end {
                return Some(offset + (col - s.start) as u32);
            }
            offset += (s.end - s.start) as u32;
        }
        None
    }

    /// Every entry that `keep` accepts (by its index in [`Subfield::entries`]) and whose rays
    /// include cell `(x, y)`, in surface order, as its index and the ray's offset within it:
    /// the surfaces the ray crosses. `keep` is asked first, so the spans of the entries it
    /// refuses are never scanned.
    pub fn entries_at<'a>(
        &'a self,
        x: u32,
        y: u32,
        keep: impl Fn(usize) -> bool + 'a,
    ) -> impl Iterator<Item = (usize, u32)> + 'a {
        let (m, n) = (self.grid.tile, self.grid.resolution);
        let inside = x < n && y < n;
        let k = if inside {
            ((y / m) * self.grid.tiles_per_side() + x / m) as usize
        } else {
            0
        };
        let (row, col) = ((y % m) as u16, (x % m) as u16);
        let entries = if inside { self.tile(k) } else { &[] };
        let first = if inside { self.tile_start[k] as usize } else { 0 };
        (entries.iter().enumerate())
            .filter(move |&(local, _)| keep(first + local))
            .filter_map(move |(local, e)| Some((first + local, self.offset_in(e, row, col)?)))
    }

    /// Visits every ray of `surface` in slot order with its grid cell `(x, y)`.
    pub fn rays_of(&self, k: usize, entry: &TileSurface, mut visit: impl FnMut(u32, u32, u32)) {
        let m = self.grid.tile;
        let per_side = self.grid.tiles_per_side() as usize;
        let (tx, ty) = ((k % per_side) as u32 * m, (k / per_side) as u32 * m);
        let mut slot = entry.first_ray;
        for s in self.spans_of(entry) {
            for c in s.start..s.end {
                visit(slot, tx + c as u32, ty + s.row as u32);
                slot += 1;
            }
        }
    }

    /// The entries of the surfaces that `keep` accepts, as a subfield of their own (the same
    /// frame, grid, tiles and spans, the rays numbered afresh): the subfield that rasterising
    /// those surfaces alone builds ([`Footprints::of`]), to the bit — a tile's entries are
    /// sorted by surface, and each surface is rasterised on its own.
    pub fn only(&self, keep: impl Fn(u32) -> bool) -> Subfield {
        let mut tile_start = Vec::with_capacity(self.tile_start.len());
        let (mut entries, mut spans) = (Vec::new(), Vec::new());
        let mut slots = 0u32;
        tile_start.push(0);
        for k in 0..self.tile_count() {
            for e in self.tile(k).iter().filter(|e| keep(e.surface)) {
                let first_span = spans.len() as u32;
                spans.extend_from_slice(self.spans_of(e));
                entries.push(TileSurface {
                    first_span,
                    first_ray: slots,
                    ..*e
                });
                slots += e.rays;
            }
            tile_start.push(entries.len() as u32);
        }
        Subfield {
            frame: self.frame,
            grid: self.grid,
            tile_start,
            entries,
            spans,
        }
    }

    /// Bytes held by this subfield's tables.
    pub fn memory_bytes(&self) -> usize {
        self.tile_start.len() * 4
            + self.entries.len() * std::mem::size_of::<TileSurface>()
            + self.spans.len() * std::mem::size_of::<Span>()
    }
}

/// Where the rays of a subfield meet one surface, as affine functions of the
/// ray's grid coordinates `(x, y)` (cell centres at `i + ½`):
/// `depth = d0 + dx·x + dy·y` along `w`, and the hit point
/// `p = p0 + px·x + py·y`. Derivation: the ray origin is
/// `r = r0 + x·(2/N)u + y·(2/N)v` ([`PsfFrame::ray_origin`]); the plane `n·p = c` gives
/// `depth = (c − n·r)/(n·w)`, affine in `(x, y)`.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceProjection {
    pub depth: [f64; 3],
    pub p0: DVec3,
    pub px: DVec3,
    pub py: DVec3,
}

impl SurfaceProjection {
    pub fn new(frame: &PsfFrame, n: u32, normal: DVec3, offset: f64) -> Self {
        let step = 2.0 / n as f64;
        let r0 = frame.ray_origin(0.0, 0.0, n);
        let (ru, rv) = (frame.u * step, frame.v * step);
        let nw = normal.dot(frame.w);
        let d0 = (offset - normal.dot(r0)) / nw;
        let dx = -normal.dot(ru) / nw;
        let dy = -normal.dot(rv) / nw;
        SurfaceProjection {
            depth: [d0, dx, dy],
            p0: r0 + frame.w * d0,
            px: ru + frame.w * dx,
            py: rv + frame.w * dy,
        }
    }

    #[inline]
    pub fn depth_at(&self, x: f64, y: f64) -> f64 {
        self.depth[0] + self.depth[1] * x + self.depth[2] * y
    }

    #[inline]
    pub fn point_at(&self, x: f64, y: f64) -> DVec3 {
        self.p0 + self.px * x + self.py * y
    }
}

/// The index of `surface` in a tile's entries (sorted by surface, each once), if it is there.
///
/// The same answer as a binary search, found with fewer reads of memory that is seldom in cache:
/// a gather table looks up one ray at a time in the mirror views of other directions
/// ([`Subfield::locate_entry`]), where a tile of a curved mirror lists hundreds of triangles
/// and each step of a binary search was a cache miss. The first probe is where `surface` would
/// be if the tile's surface numbers were spread evenly between its first and last (they are
/// near enough: a mesh numbers neighbouring triangles closely); from there the search gallops
/// (steps 1, 2, 4, … away) until it brackets `surface`, then bisects the bracket. At worst
/// that is twice a binary search's steps; where the guess is close, three or four reads.
fn find_surface(entries: &[TileSurface], surface: u32) -> Option<usize> {
    let (first, last) = (entries.first()?.surface, entries.last()?.surface);
    if surface < first || surface > last {
        return None;
    }
    if surface == last {
        return Some(entries.len() - 1);
    }
    // `first <= surface < last`, so the guess is in 0..len - 1 and the answer in 0..len - 1.
    let span = u64::from(last - first);
    let guess = (u64::from(surface - first) * (entries.len() as u64 - 1) / span) as usize;
    let (mut lo, mut hi) = if entries[guess].surface <= surface {
        // Gallop up from `guess`: the answer is at or past it.
        let (mut lo, mut step) = (guess, 1usize);
        loop {
            let probe = lo + step;
            if probe >= entries.len() || entries[probe].surface > surface {
                break (lo, probe.min(entries.len()));
            }
            (lo, step) = (probe, step * 2);
        }
    } else {
        // Gallop down: the answer is before `guess`.
        let (mut hi, mut step) = (guess, 1usize);
        loop {
            match hi.checked_sub(step) {
                Some(probe) if entries[probe].surface > surface => (hi, step) = (probe, step * 2),
                Some(probe) => break (probe, hi),
                None => break (0, hi),
            }
        }
    };
    // `entries[lo].surface <= surface < entries[hi].surface` (or `hi` the end; the downward
    // gallop's `lo = 0` too, as `first <= surface`): bisect, then compare.
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if entries[mid].surface <= surface {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    (entries[lo].surface == surface).then_some(lo)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{FaceOrigin, Material, Normalisation, Scene, Surface};

    /// The guided search answers as a binary search does, for every number from below the first
    /// surface to past the last, on lists spread evenly, clustered at either end (where the
    /// first guess is far off and the gallop goes the whole way), one long, and of one or none.
    #[test]
    fn find_surface_answers_as_a_binary_search() {
        let entry = |surface| TileSurface {
            surface,
            first_span: 0,
            span_count: 0,
            rays: 0,
            first_ray: 0,
        };
        let mut lists: Vec<Vec<u32>> = vec![vec![], vec![5], vec![3, 4], (0..50).map(|k| 7 * k + 2).collect()];
        // Clustered low with one outlier high, and the reverse.
        lists.push((0..40).chain([100_000]).collect());
        lists.push([0].into_iter().chain(99_960..100_000).collect());
        // Irregular gaps from a fixed hash.
        let mut v = 0u32;
        lists.push(
            (0..300)
                .map(|k: u32| {
                    v += 1 + (k.wrapping_mul(2_654_435_761) >> 24) % 97;
                    v
                })
                .collect(),
        );
        // Numbers up to the largest, where the guess's product needs 64 bits.
        lists.push(vec![0, 1, u32::MAX - 1, u32::MAX]);
        lists.push((0..300u32).map(|k| k * (u32::MAX / 300)).chain([u32::MAX]).collect());
        for list in &lists {
            let entries: Vec<TileSurface> = list.iter().map(|&s| entry(s)).collect();
            // Every number of a short range, else each surface, its neighbours and a midpoint.
            let top = list.last().copied().unwrap_or(0).saturating_add(3);
            let probes: Vec<u32> = if top < 1 << 20 {
                (0..=top).collect()
            } else {
                (list.iter().zip(list.iter().skip(1)))
                    .flat_map(|(&a, &b)| [a.saturating_sub(1), a, a + 1, a + (b - a) / 2, b])
                    .chain([0, u32::MAX])
                    .collect()
            };
            for surface in probes {
                let expected = entries.binary_search_by_key(&surface, |e| e.surface).ok();
                assert_eq!(find_surface(&entries, surface), expected, "{surface} in {list:?}");
            }
        }
    }

    fn tri(a: DVec3, b: DVec3, c: DVec3) -> Surface {
        let n = (b - a).cross(c - a);
        Surface {
            vertices: vec![a, b, c],
            normal: n.normalize(),
            offset: n.normalize().dot(a),
            area: n.length() / 2.0,
            material: 0,
            origin: FaceOrigin { line: 0, face: 0 },
            uv: None,
        }
    }

    fn scene() -> Scene {
        let mut surfaces = Vec::new();
        // A fan of triangles around a point (shared edges), tilted.
        let centre = DVec3::new(0.1, -0.05, 0.2);
        for k in 0..7 {
            let a0 = k as f64 / 7.0 * std::f64::consts::TAU;
            let a1 = (k + 1) as f64 / 7.0 * std::f64::consts::TAU;
            let p = |a: f64| DVec3::new(0.7 * a.cos(), 0.6 * a.sin(), 0.3 * a.cos() * a.sin());
            surfaces.push(tri(centre, p(a0), p(a1)));
        }
        Scene {
            surfaces,
            materials: vec![Material {
                name: "m".into(),
                diffuse: [0.5; 3],
                specular: [0.0; 3],
                emission: [1.0; 3],
                albedo_texture: None,
            }],
            normalisation: Normalisation {
                center: DVec3::ZERO,
                scale: 1.0,
            },
            textures: Vec::new(),
        }
    }

    #[test]
    fn frame_is_orthonormal_and_right_handed() {
        for w in [
            DVec3::X,
            DVec3::Y,
            DVec3::Z,
            DVec3::new(0.3, -0.5, 0.8),
            DVec3::new(-1.0, 1e-9, 0.0),
        ] {
            let f = PsfFrame::new(w);
            assert!((f.u.length() - 1.0).abs() < 1e-12 && (f.v.length() - 1.0).abs() < 1e-12);
            assert!(f.u.dot(f.v).abs() < 1e-12 && f.u.dot(f.w).abs() < 1e-12);
            assert!((f.u.cross(f.v) - f.w).length() < 1e-12);
        }
    }

    /// The tiles hold exactly the rays the whole-grid rasterisation covers,
    /// each span inside its tile, surfaces sorted within a tile.
    #[test]
    fn tiles_partition_the_rasterisation() {
        let scene = scene();
        for (n, m) in [(32, 8), (64, 8), (48, 16), (16, 16), (30, 5)] {
            let grid = GridSize::new(n, m).unwrap();
            let w = DVec3::new(0.2, 0.3, 0.9).normalize();
            let reps: Vec<u32> = (0..scene.surfaces.len() as u32).collect();
            let frame = PsfFrame::with_shift(w, DVec2::new(0.37, -0.21));
            let sub = Subfield::build(&Footprints::new(&scene, &reps), frame, grid);
            assert_eq!(sub.tile_count(), ((n / m) * (n / m)) as usize);
            let mut per_surface = vec![0u64; scene.surfaces.len()];
            for k in 0..sub.tile_count() {
                let entries = sub.tile(k);
                assert!(entries.windows(2).all(|e| e[0].surface < e[1].surface));
                for e in entries {
                    let mut rays = 0;
                    for s in sub.spans_of(e) {
                        assert!(s.start < s.end && (s.end as u32) <= m && (s.row as u32) < m);
                        rays += (s.end - s.start) as u32;
                    }
                    assert_eq!(rays, e.rays);
                    per_surface[e.surface as usize] += rays as u64;
                }
            }
            for (id, s) in scene.surfaces.iter().enumerate() {
                let pts: Vec<DVec2> = s.vertices.iter().map(|&p| sub.frame.to_grid(p, n)).collect();
                assert_eq!(
                    per_surface[id],
                    raster::rasterize_convex(&pts, n, |_| {}),
                    "surface {id}, N={n}"
                );
            }
            assert!(per_surface.iter().all(|&r| r > 0), "a triangle of the fan was missed");
            // Slots: rays_of and locate agree, and slots are 0..slot_count.
            let mut seen = vec![false; sub.slot_count()];
            for k in 0..sub.tile_count() {
                for e in sub.tile(k) {
                    sub.rays_of(k, e, |slot, x, y| {
                        assert_eq!(sub.locate(e.surface, x, y), Some(slot));
                        assert!(!seen[slot as usize]);
                        seen[slot as usize] = true;
                    });
                }
            }
            assert!(seen.iter().all(|&s| s));
            assert_eq!(sub.locate(0, n, 0), None);
        }
    }

    /// Depth and hit point from the affine projection lie on the surface plane
    /// and on the ray.
    #[test]
    fn projection_hits_the_plane_on_the_ray() {
        let scene = scene();
        let n = 64;
        let frame = PsfFrame::with_shift(DVec3::new(-0.4, 0.1, 0.7), DVec2::new(-0.5, 0.3));
        for s in &scene.surfaces {
            let p = SurfaceProjection::new(&frame, n, s.normal, s.offset);
            for (x, y) in [(0.5, 0.5), (10.5, 40.5), (63.5, 2.5)] {
                let hit = p.point_at(x, y);
                assert!((s.normal.dot(hit) - s.offset).abs() < 1e-9);
                let origin = frame.ray_origin(x, y, n);
                assert!((origin + frame.w * p.depth_at(x, y) - hit).length() < 1e-9);
            }
        }
    }
}
