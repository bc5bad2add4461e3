//! Mirrors "from the rays" on the GPU: the field's directional radiance maps and what is needed
//! to find a ray again, packed into one `array<u32>` for the shader (`shaders/field.wgsl`,
//! `mirror_from_rays`), which re-implements `LightField::mirror_radiance_from_rays`:
//!
//! 1. The outgoing direction lies in a spherical triangle of three line directions with
//!    barycentric weights (`DirectionSet::triangle`: the octahedral lattice table, its
//!    rotation and the unit vectors are uploaded as they are).
//! 2. In each direction's subfield the point projects between four rays; each ray's mirror slot
//!    is read from a dense *window* per (direction, mirror plane) — the rectangle of the ray
//!    cells that a look-up on the plane's polygons reads and that have a slot, holding the slot
//!    `LightField::mirror_slot` gives (the plane's own crossing, or a neighbouring mirror's on a
//!    curved mirror), or `NONE` — and the rays' radiance is interpolated bilinearly over the
//!    rays that exist.
//! 3. The three are blended by the barycentric weights of the directions that had a ray.
//!
//! The windows replace the CPU's tile lists and span search by one indexed read; they hold
//! about as many cells as the mirrors have slots (the rectangles' fill).
//!
//! The radiance itself is not here: a cell names the *part* holding its ray (the mirror tile,
//! `vlf_core::parts`) and the ray's place in it; the part's values lie wherever the renderer's
//! pool put them (`FieldRenderer::upload`), or nowhere yet while a viewer streams them.
//!
//! Layout of the words (offsets in words, floats as their bits):
//!
//! | words | what |
//! |---|---|
//! | 0..16 | header: `n`, `l`, mirrors, resolution `N`, offsets of lattice, vectors, directions, windows, cells; rotation (9 floats, column-major) from word 16 |
//! | lattice | `(2n+1)²` words: line direction index, bit 31 set for `−ω`; `NONE` outside |
//! | vectors | 3 floats per line direction: its unrotated unit vector |
//! | directions | 8 words per line direction: PSF frame `u`, `v` (3 floats each), then the ray lattice's phase `shift` (2 floats) |
//! | windows | 5 words per (direction, mirror plane): `x0`, `y0`, width, height, first cell |
//! | cells | two words per ray cell of a window: the part holding the ray and its index in the part, or `NONE`, `NONE` |

use rayon::prelude::*;
use vlf_core::field::LightField;
use vlf_core::parts::{Part, PartCatalog};

/// No slot, no direction.
pub const NONE: u32 = u32::MAX;
const HEADER_WORDS: usize = 32;

/// The words, and the mirror plane index of every surface (`NONE` for a non-mirror).
pub struct RayTables {
    pub words: Vec<u32>,
    pub mirror_index: Vec<u32>,
}

impl RayTables {
    /// The tables of `field`, whose parts `catalog` numbers; a field without mirror maps gets a
    /// header only (nothing reads it).
    pub fn new(field: &LightField, catalog: &PartCatalog) -> RayTables {
        let scene = &field.scene;
        // One window per mirror plane: the polygons of a tessellated mirror share their plane's
        // rays (`TexelAtlas::plane_rep`), so they share its windows too. Representatives come
        // first in their plane, so every polygon finds its plane's index already given.
        let plane_rep = &field.atlas.plane_rep;
        let mut mirror_index = vec![NONE; scene.surfaces.len()];
        let mut mirror_surfaces = Vec::new();
        for i in 0..scene.surfaces.len() {
            if scene.material(i).is_mirror() {
                let rep = plane_rep.get(i).map_or(i, |&r| r as usize);
                mirror_index[i] = if rep == i || mirror_index[rep] == NONE {
                    mirror_surfaces.push(i as u32);
                    mirror_surfaces.len() as u32 - 1
                } else {
                    mirror_index[rep]
                };
            }
        }
        let mirrors = mirror_surfaces.len() as u32;
        let mut words = vec![0u32; HEADER_WORDS];
        let Some(spec) = &field.specular else {
            return RayTables { words, mirror_index };
        };
        let (n, rotation, lattice, vectors) = spec.directions.lookup_tables();
        let l = spec.subfields.len();
        let resolution = spec.subfields.grid().resolution;
        let f = |v: f64| (v as f32).to_bits();
        words[0] = n as u32;
        words[1] = l as u32;
        words[2] = mirrors;
        words[3] = resolution;
        for (k, v) in rotation.to_cols_array().iter().enumerate() {
            words[16 + k] = f(*v);
        }

        words[4] = words.len() as u32;
        words.extend(lattice.iter().map(|o| {
            if o.index == u32::MAX {
                NONE
            } else {
                o.index | (u32::from(o.reversed) << 31)
            }
        }));

        words[5] = words.len() as u32;
        words.extend(vectors.iter().flat_map(|v| v.to_array().map(f)));

        words[6] = words.len() as u32;
        for d in 0..l {
            let frame = spec.subfields.frame(d);
            words.extend(frame.u.to_array().map(f));
            words.extend(frame.v.to_array().map(f));
            words.extend(frame.shift.to_array().map(f));
        }

        // Windows: the rectangle of ray cells each mirror plane's look-ups read, per direction
        // (in parallel: a curved mirror has a plane per triangle), then laid end to end.
        let planes = Planes {
            index: &mirror_index,
            surfaces: &mirror_surfaces,
        };
        let per_direction: Vec<(Vec<u32>, Vec<u32>)> = (0..l)
            .into_par_iter()
            .map(|d| direction_windows(field, catalog, d, &planes))
            .collect();
        let mut windows = Vec::with_capacity(l * mirrors as usize * 5);
        let mut cells = Vec::new();
        for (w, c) in per_direction {
            let first = cells.len() as u32 / 2;
            for window in w.chunks_exact(5) {
                let shift = if window[2] == 0 { 0 } else { first };
                windows.extend([window[0], window[1], window[2], window[3], window[4] + shift]);
            }
            cells.extend(c);
        }
        words[7] = words.len() as u32;
        words.extend(windows);
        words[8] = words.len() as u32;
        words.extend(cells);
        RayTables { words, mirror_index }
    }
}

/// The mirror planes the windows are kept for: the plane index of every surface (`NONE` for a
/// non-mirror) and each plane's first polygon.
struct Planes<'a> {
    index: &'a [u32],
    surfaces: &'a [u32],
}

/// Direction `d`'s windows (5 words per mirror plane, its first cell counted from the
/// direction's first) and cells (two words each).
fn direction_windows(field: &LightField, catalog: &PartCatalog, d: usize, planes: &Planes) -> (Vec<u32>, Vec<u32>) {
    let Some(spec) = &field.specular else {
        return (Vec::new(), Vec::new());
    };
    let sub = &spec.subfields.get(d);
    let layout = &spec.layouts[d];
    let (tile_size, per_side) = (sub.grid.tile, sub.grid.tiles_per_side());
    let resolution = sub.grid.resolution;
    // The part holding the ray of cell (x, y) at `slot`, and the ray's index in it.
    let place = |x: u32, y: u32, slot: u32| {
        let part = catalog.index_of(Part::Tile {
            direction: d as u32,
            tile: (y / tile_size) * per_side + x / tile_size,
        });
        match part {
            Some(part) => [part, slot - catalog.range(part).start as u32],
            None => [NONE, NONE],
        }
    };
    // Every ray's mirror crossings as (surface, slot), listed once: what `mirror_slot` would
    // search its tile for at every cell of every plane's window.
    let n = resolution as usize;
    let mut crossings: Vec<Vec<(u32, u32)>> = vec![Vec::new(); n * n];
    for &(surface, k, entry) in &layout.entries {
        let e = &sub.entries[entry as usize];
        let base = layout.entry_base[entry as usize];
        sub.rays_of(k as usize, e, |slot, x, y| {
            crossings[y as usize * n + x as usize].push((surface, base + slot - e.first_ray));
        });
    }
    // Where a look-up on each mirror plane can read: the four rays around any point of its
    // polygons (the polygons' vertices projected, as `mirror_rays` projects a point, and one ray
    // further on the high side).
    let mirrors = planes.surfaces.len();
    let mut bounds = vec![(i64::MAX, i64::MAX, i64::MIN, i64::MIN); mirrors];
    for (surface, &m) in field.scene.surfaces.iter().zip(planes.index) {
        if m == NONE {
            continue;
        }
        let b = &mut bounds[m as usize];
        for &v in &surface.vertices {
            let g = (sub.frame.to_grid(v, resolution) - 0.5).floor();
            let (x, y) = (g.x as i64, g.y as i64);
            *b = (b.0.min(x), b.1.min(y), b.2.max(x + 2), b.3.max(y + 2));
        }
    }
    let plane_rep = &field.atlas.plane_rep;
    let (mut windows, mut cells) = (Vec::with_capacity(mirrors * 5), Vec::new());
    for (m, &(x0, y0, x1, y1)) in bounds.iter().enumerate() {
        let clamp = |v: i64| v.clamp(0, resolution as i64) as u32;
        let (x0, y0, x1, y1) = (clamp(x0), clamp(y0), clamp(x1), clamp(y1));
        // The slot every cell stands for (`LightField::mirror_slot`: the plane's own ray, or a
        // neighbouring mirror's), then the window trimmed to the cells that have one.
        let surface = planes.surfaces[m];
        let rep = plane_rep.get(surface as usize).copied().unwrap_or(surface);
        let width = x1.saturating_sub(x0) as usize;
        let slots: Vec<Option<u32>> = (y0..y1)
            .flat_map(|y| (x0..x1).map(move |x| (x, y)))
            .map(|(x, y)| {
                let here = &crossings[y as usize * n + x as usize];
                match here.iter().find(|c| c.0 == rep) {
                    Some(&(_, slot)) => Some(slot),
                    None => field.neighbour_slot(sub, surface, x, y, here.iter().copied()),
                }
            })
            .collect();
        let mut used = (u32::MAX, u32::MAX, 0u32, 0u32);
        for (i, _) in slots.iter().enumerate().filter(|(_, s)| s.is_some()) {
            let (x, y) = (x0 + (i % width) as u32, y0 + (i / width) as u32);
            used = (used.0.min(x), used.1.min(y), used.2.max(x + 1), used.3.max(y + 1));
        }
        if used.0 == u32::MAX {
            windows.extend([0, 0, 0, 0, 0]);
            continue;
        }
        let (ux0, uy0, ux1, uy1) = used;
        windows.extend([ux0, uy0, ux1 - ux0, uy1 - uy0, cells.len() as u32 / 2]);
        for y in uy0..uy1 {
            for x in ux0..ux1 {
                let i = (y - y0) as usize * width + (x - x0) as usize;
                cells.extend(match slots[i] {
                    Some(slot) => place(x, y, slot),
                    None => [NONE, NONE],
                });
            }
        }
    }
    (windows, cells)
}
