//! Mirrors "from the rays" on the GPU: the field's directional radiance maps and what is needed
//! to find a ray again, packed into one `array<u32>` for the shader (`shaders/field.wgsl`,
//! `mirror_from_rays`), which re-implements `LightField::mirror_radiance_from_rays`:
//!
//! 1. The outgoing direction lies in a spherical triangle of three line directions with
//!    barycentric weights (`DirectionSet::triangle`: the octahedral lattice table, its
//!    rotation and the unit vectors are uploaded as they are).
//! 2. In each direction's subfield the point projects between four rays; each ray's mirror slot
//!    is read from a dense *window* per (direction, mirror) — the rectangle of ray cells the
//!    mirror plane covers (its polygons share it) and one more on every side, holding where
//!    `MirrorLayout::locate_on_plane` puts the ray, or `NONE` — and the
//!    rays' radiance is interpolated bilinearly over the rays that exist.
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

        // Windows: the rectangle of ray cells each mirror covers in each direction.
        let mut windows = Vec::with_capacity(l * mirrors as usize);
        let mut cells = Vec::new();
        for (d, layout) in spec.layouts.iter().enumerate() {
            let sub = &spec.subfields.get(d);
            let (tile_size, per_side) = (sub.grid.tile, sub.grid.tiles_per_side());
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
            let mut bounds = vec![(u32::MAX, u32::MAX, 0u32, 0u32); mirrors as usize];
            for &(surface, k, entry) in &layout.entries {
                let m = mirror_index[surface as usize];
                if m == NONE || mirror_surfaces[m as usize] != surface {
                    continue;
                }
                let b = &mut bounds[m as usize];
                sub.rays_of(k as usize, &sub.entries[entry as usize], |_, x, y| {
                    *b = (b.0.min(x), b.1.min(y), b.2.max(x + 1), b.3.max(y + 1));
                });
            }
            let resolution = sub.grid.resolution;
            for (m, &(x0, y0, x1, y1)) in bounds.iter().enumerate() {
                if x0 == u32::MAX {
                    windows.extend([0, 0, 0, 0, 0]);
                    continue;
                }
                // One more ray on every side: a look-up near the mirror's edge may read a ray
                // just past it (its point projects between four rays).
                let (x0, y0) = (x0.saturating_sub(1), y0.saturating_sub(1));
                let (x1, y1) = ((x1 + 1).min(resolution), (y1 + 1).min(resolution));
                let surface = mirror_surfaces[m];
                windows.extend([x0, y0, x1 - x0, y1 - y0, cells.len() as u32 / 2]);
                for y in y0..y1 {
                    for x in x0..x1 {
                        cells.extend(
                            match layout.locate_on_plane(sub, &field.atlas.plane_rep, surface, x, y) {
                                Some(slot) => place(x, y, slot),
                                None => [NONE, NONE],
                            },
                        );
                    }
                }
            }
        }
        words[7] = words.len() as u32;
        words.extend(windows);
        words[8] = words.len() as u32;
        words.extend(cells);
        RayTables { words, mirror_index }
    }
}
