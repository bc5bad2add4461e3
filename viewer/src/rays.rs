//! Mirrors "from the rays" on the GPU: the field's directional radiance maps and what is needed
//! to find a ray again, packed into one `array<u32>` for the shader (`shaders/field.wgsl`,
//! `mirror_from_rays`), which re-implements `LightField::mirror_radiance_from_rays`:
//!
//! 1. The outgoing direction lies in a spherical triangle of three line directions with
//!    barycentric weights (`DirectionSet::triangle`: the octahedral lattice table, its
//!    rotation and the unit vectors are uploaded as they are).
//! 2. In each direction's subfield the point projects between four rays; each ray's mirror slot
//!    is the one `LightField::mirror_slot` gives: the ray's crossing of the polygon's mirror
//!    plane, or, where the ray misses that plane (a curved mirror's small triangles), the
//!    nearest crossing of a neighbouring mirror (`LightField::neighbour_slot`: the shader
//!    applies the same rule, in f32). The rays' radiance is interpolated bilinearly over the
//!    rays that have a slot.
//! 3. The three are blended by the barycentric weights of the directions that had a ray.
//!
//! So the shader needs every ray's mirror crossings. They are listed per direction, tile by
//! tile as the subfields are cut: a tile no mirror crosses costs one word, a crossed tile one
//! word per ray (where its crossings start) and three per crossing. Beyond the one word per
//! tile of every direction (l·(N/m)²: 34 MB at l = 8193, N = 256, m = 8), that grows with the
//! mirror slots, not with the mirror polygons: the 47 794-triangle mirror dragon at l = 513, N = 64
//! takes 4.2 MB, built in 0.02 s, where dense windows per (direction, mirror plane) took 508 MB
//! and 5 s (1 064 MB and 18 s once they held the neighbours' slots), more than a GPU binds.
//!
//! The radiance itself is not here: a crossing names the *part* holding its ray (the mirror
//! tile, `vlf_core::parts`) and the ray's place in it; the part's values lie wherever the
//! renderer's pool put them (`FieldRenderer::upload`), or nowhere yet while a viewer streams
//! them.
//!
//! Layout of the words (offsets in words, floats as their bits):
//!
//! | words | what |
//! |---|---|
//! | 0..16 | header: `n`, `l`, mirror planes, resolution `N`, offsets of lattice, vectors, directions, tiles, rays, crossings; tile size `m`, tiles per side; the neighbour rule's reach (ray spacings) and least cosine (`vlf_core::lookup`); rotation (9 floats, column-major) from word 16 |
//! | lattice | `(2n+1)²` words: line direction index, bit 31 set for `−ω`; `NONE` outside |
//! | vectors | 3 floats per line direction: its unrotated unit vector |
//! | directions | 8 words per line direction: PSF frame `u`, `v` (3 floats each), then the ray lattice's phase `shift` (2 floats) |
//! | tiles | per line direction, per tile of its subfield (row-major): where the tile's rays start in `rays`, or `NONE` when no mirror crosses the tile |
//! | rays | per crossed tile, `m² + 1` words: where each of its rays' crossings start in `crossings` (row-major), then where the last one's end |
//! | crossings | 3 words per (ray, mirror plane) crossing: the plane's first polygon, the part holding the ray, the ray's index in the part |

use rayon::prelude::*;
use vlf_core::field::LightField;
use vlf_core::lookup::{NEIGHBOUR_ANGLE_COS, NEIGHBOUR_DEPTH_CELLS};
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
        // An index per mirror plane: the polygons of a tessellated mirror share their plane's
        // rays (`TexelAtlas::plane_rep`), so a look-up on any of them reads the plane's
        // crossings. Representatives come first in their plane, so every polygon finds its
        // plane's index already given.
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
        let l = spec.views.len();
        let grid = spec.views.first().map_or(field.options.grid, |v| v.sub.grid);
        let resolution = grid.resolution;
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
            let frame = spec.views[d].sub.frame;
            words.extend(frame.u.to_array().map(f));
            words.extend(frame.v.to_array().map(f));
            words.extend(frame.shift.to_array().map(f));
        }

        // Every ray's mirror crossings, per direction (in parallel), then laid end to end.
        let per_direction: Vec<DirectionCrossings> = (0..l)
            .into_par_iter()
            .map(|d| DirectionCrossings::new(field, catalog, d))
            .collect();
        words[10] = grid.tile;
        words[11] = grid.tiles_per_side();
        words[12] = f(NEIGHBOUR_DEPTH_CELLS);
        words[13] = f(NEIGHBOUR_ANGLE_COS);
        let (mut tiles, mut rays, mut crossings) = (Vec::new(), Vec::new(), Vec::new());
        for c in per_direction {
            let (first_ray, first_crossing) = (rays.len() as u32, crossings.len() as u32 / 3);
            tiles.extend(c.tiles.iter().map(|&t| if t == NONE { NONE } else { t + first_ray }));
            rays.extend(c.rays.iter().map(|&r| r + first_crossing));
            crossings.extend(c.crossings);
        }
        words[7] = words.len() as u32;
        words.extend(tiles);
        words[8] = words.len() as u32;
        words.extend(rays);
        words[9] = words.len() as u32;
        words.extend(crossings);
        RayTables { words, mirror_index }
    }
}

/// One direction's share of the tables (see the module docs), counted from its own start.
struct DirectionCrossings {
    tiles: Vec<u32>,
    rays: Vec<u32>,
    crossings: Vec<u32>,
}

impl DirectionCrossings {
    fn new(field: &LightField, catalog: &PartCatalog, d: usize) -> DirectionCrossings {
        let Some(spec) = &field.specular else {
            return DirectionCrossings {
                tiles: Vec::new(),
                rays: Vec::new(),
                crossings: Vec::new(),
            };
        };
        let (sub, layout) = (&spec.views[d].sub, &spec.views[d].layout);
        let (m, per_side, n) = (sub.grid.tile, sub.grid.tiles_per_side(), sub.grid.resolution);
        // Each ray's crossings as (plane, slot), from the mirror entries of its tile.
        let mut of_ray: Vec<Vec<(u32, u32)>> = vec![Vec::new(); (n * n) as usize];
        for &(surface, k, entry) in &layout.entries {
            let e = &sub.entries[entry as usize];
            let base = layout.entry_base[entry as usize];
            sub.rays_of(k as usize, e, |slot, x, y| {
                of_ray[(y * n + x) as usize].push((surface, base + slot - e.first_ray));
            });
        }
        let mut tiles = vec![NONE; (per_side * per_side) as usize];
        let (mut rays, mut crossings) = (Vec::new(), Vec::new());
        for (k, tile) in tiles.iter_mut().enumerate() {
            let (tx, ty) = ((k as u32 % per_side) * m, (k as u32 / per_side) * m);
            let cells = (0..m * m).map(|r| (tx + r % m, ty + r / m));
            if cells
                .clone()
                .all(|(x, y)| x >= n || y >= n || of_ray[(y * n + x) as usize].is_empty())
            {
                continue;
            }
            *tile = rays.len() as u32;
            // The part holding the tile's rays.
            let part = catalog.index_of(Part::Tile {
                direction: d as u32,
                tile: k as u32,
            });
            for (x, y) in cells {
                rays.push(crossings.len() as u32 / 3);
                if x >= n || y >= n {
                    continue;
                }
                for &(surface, slot) in &of_ray[(y * n + x) as usize] {
                    crossings.extend(match part {
                        Some(part) => [surface, part, slot - catalog.range(part).start as u32],
                        None => [surface, NONE, NONE],
                    });
                }
            }
            rays.push(crossings.len() as u32 / 3);
        }
        DirectionCrossings { tiles, rays, crossings }
    }
}
