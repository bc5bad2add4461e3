//! How a field's radiance is cut into *parts*: the unit in which it is stored, fetched and kept
//! resident by a viewer.
//!
//! | part | values | where in the field |
//! |---|---|---|
//! | `Chunk(c)` | the diffuse maps of a run of consecutive charts ([`TexelAtlas::chunks`]) | `radiance[first ..]` of its first chart's grid |
//! | `Tile { direction: d, tile: k }` | the mirror slots of tile `k` of subfield `d` | `totals[d][range]` |
//!
//! A tile's slots are contiguous because a [`MirrorLayout`](crate::propagate::specular::MirrorLayout)
//! numbers slots tile by tile ([`MirrorLayout::tile_slots`](crate::propagate::specular::MirrorLayout::tile_slots));
//! only tiles that hold mirror slots are parts. Diffuse maps are cut into chunks of at most
//! [`DIFFUSE_CHUNK_TEXELS`] texels (a chart larger than that is a chunk of its own), so that
//! their number follows the texels, not the polygon count: a scan of 10⁵ triangles is a few
//! chunks, not 10⁵ blobs. The store writes one blob per part of a final field; [`LightField::view_needs`] says which parts a view reads, so a viewer can hold only
//! those.
//!
//! Everything but the radiance is a deterministic function of the scene and the options, so the
//! [`PartCatalog`] of a field built from them alone (radiance zero) is the same as the complete
//! field's: a viewer builds it before any radiance has arrived.

use crate::field::LightField;
use crate::lookup::ViewNeeds;
use crate::maps::TexelAtlas;
use std::collections::HashMap;
use std::ops::Range;

/// Most texels in one chunk of diffuse maps: 768 KiB of f32 RGB, 384 KiB in f16.
pub const DIFFUSE_CHUNK_TEXELS: usize = 1 << 16;

/// One part of a field's radiance (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Part {
    /// The diffuse maps of chunk `c` (a run of charts).
    Chunk(u32),
    /// The mirror slots of tile `tile` of line direction `direction`.
    Tile { direction: u32, tile: u32 },
}

/// Every part of a field, numbered: chunks of diffuse maps first (part `i` is chunk `i`), then
/// mirror tiles direction by direction, tile by tile. With each, where its values lie in the
/// field.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PartCatalog {
    parts: Vec<Part>,
    ranges: Vec<Range<usize>>,
    index: HashMap<Part, u32>,
    /// The chunk of every chart.
    chunk_of_chart: Vec<u32>,
    /// The chunk of every surface (its chart's).
    chunk_of_surface: Vec<u32>,
}

/// The chunks of `atlas`' diffuse maps: for each, its charts and its texels (one contiguous
/// range of the atlas).
pub fn diffuse_chunks(atlas: &TexelAtlas) -> Vec<(Range<u32>, Range<usize>)> {
    atlas
        .chunks(DIFFUSE_CHUNK_TEXELS)
        .into_iter()
        .map(|charts| {
            let first = atlas.charts[charts.start as usize].first;
            let last = &atlas.charts[charts.end as usize - 1];
            (charts, first..last.first + last.len())
        })
        .collect()
}

impl PartCatalog {
    /// The parts of `field` (only its geometry is read).
    pub fn new(field: &LightField) -> PartCatalog {
        let mut parts = Vec::new();
        let mut ranges = Vec::new();
        let mut chunk_of_chart = vec![0u32; field.atlas.charts.len()];
        for (c, (charts, texels)) in diffuse_chunks(&field.atlas).into_iter().enumerate() {
            parts.push(Part::Chunk(c as u32));
            ranges.push(texels);
            chunk_of_chart[charts.start as usize..charts.end as usize].fill(c as u32);
        }
        let chunk_of_surface = field
            .atlas
            .chart_of
            .iter()
            .map(|&c| chunk_of_chart[c as usize])
            .collect();
        if let Some(spec) = &field.specular {
            for (d, view) in spec.views.iter().enumerate() {
                for (k, range) in view.layout.tile_slots(&view.sub) {
                    parts.push(Part::Tile {
                        direction: d as u32,
                        tile: k,
                    });
                    ranges.push(range);
                }
            }
        }
        let index = parts.iter().enumerate().map(|(i, &p)| (p, i as u32)).collect();
        PartCatalog {
            parts,
            ranges,
            index,
            chunk_of_chart,
            chunk_of_surface,
        }
    }

    /// The chunk part holding `surface`'s diffuse map.
    pub fn chunk_of_surface(&self, surface: usize) -> u32 {
        self.chunk_of_surface[surface]
    }

    /// The chunk part holding chart `chart`'s diffuse map.
    pub fn chunk_of_chart(&self, chart: usize) -> u32 {
        self.chunk_of_chart[chart]
    }

    /// Number of chunks of diffuse maps (parts `0..chunks`).
    pub fn chunks(&self) -> usize {
        self.parts.iter().take_while(|p| matches!(p, Part::Chunk(_))).count()
    }

    /// Number of parts.
    pub fn len(&self) -> usize {
        self.parts.len()
    }

    pub fn is_empty(&self) -> bool {
        self.parts.is_empty()
    }

    /// The parts, in catalog order.
    pub fn parts(&self) -> &[Part] {
        &self.parts
    }

    /// Part number `i`.
    pub fn part(&self, i: u32) -> Part {
        self.parts[i as usize]
    }

    /// The number of `part`, if the field has it.
    pub fn index_of(&self, part: Part) -> Option<u32> {
        self.index.get(&part).copied()
    }

    /// Where part `i`'s values lie: in [`LightField::radiance`] for a chunk, in
    /// `totals[direction]` for a tile.
    pub fn range(&self, i: u32) -> Range<usize> {
        self.ranges[i as usize].clone()
    }

    /// How many RGB values part `i` holds.
    pub fn values(&self, i: u32) -> usize {
        self.ranges[i as usize].len()
    }

    /// RGB values of all parts together (a complete field's radiance and mirror totals).
    pub fn total_values(&self) -> usize {
        self.ranges.iter().map(|r| r.len()).sum()
    }

    /// The numbers of the parts `needs` lists, coarse first: the chunks of the diffuse maps of
    /// its surfaces (they draw every surface and, through traced reflections, the mirrors),
    /// then mirror tiles by how much of the image they make ([`ViewNeeds::tile_weight`],
    /// heaviest first; ties in tile order).
    pub fn needed(&self, needs: &ViewNeeds) -> Vec<u32> {
        let mut chunks: Vec<u32> = (needs.surfaces.iter())
            .filter_map(|&s| self.chunk_of_surface.get(s as usize).copied())
            .collect();
        chunks.sort_unstable();
        chunks.dedup();
        let surfaces = chunks.into_iter().map(Part::Chunk);
        let mut tiles: Vec<(u32, u32)> = needs.mirror_tiles.iter().copied().collect();
        let weight = |t: &(u32, u32)| needs.tile_weight.get(t).copied().unwrap_or(0.0);
        tiles.sort_by(|a, b| weight(b).total_cmp(&weight(a)).then(a.cmp(b)));
        let tiles = tiles
            .into_iter()
            .map(|(direction, tile)| Part::Tile { direction, tile });
        surfaces.chain(tiles).filter_map(|p| self.index_of(p)).collect()
    }
}

impl LightField {
    /// The values of part `i` of `catalog` (this field's).
    pub fn part_values(&self, catalog: &PartCatalog, i: u32) -> &[[f32; 3]] {
        let range = catalog.range(i);
        match catalog.part(i) {
            Part::Chunk(_) => &self.radiance[range],
            Part::Tile { direction, .. } => match &self.specular {
                Some(spec) => &spec.totals[direction as usize][range],
                None => &[],
            },
        }
    }

    /// Mutable [`LightField::part_values`]: where a reader puts a part it has read.
    pub fn part_values_mut(&mut self, catalog: &PartCatalog, i: u32) -> &mut [[f32; 3]] {
        let range = catalog.range(i);
        match catalog.part(i) {
            Part::Chunk(_) => &mut self.radiance[range],
            Part::Tile { direction, .. } => match &mut self.specular {
                Some(spec) => &mut spec.totals[direction as usize][range],
                None => &mut [],
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::propagate::{Options, Propagation, Stop};
    use crate::psf::GridSize;
    use crate::scene::{ImportOptions, load_obj};

    /// The bundled mirror scene, coarse: both kinds of parts.
    fn field() -> LightField {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/mirrors.obj");
        let (scene, _) = load_obj(&path, &ImportOptions::default()).unwrap();
        let options = Options {
            directions: 9,
            grid: GridSize::new(16, 4).unwrap(),
            stop: Stop::Iterations(2),
            ..Options::default()
        };
        let mut p = Propagation::new(scene, options).unwrap();
        p.run(|_| {});
        p.into_field()
    }

    #[test]
    fn parts_tile_the_field_exactly_once() {
        let field = field();
        let catalog = PartCatalog::new(&field);
        let spec = field.specular.as_ref().expect("mirrors");
        // Every texel and every mirror slot belongs to exactly one part.
        let mut texels = vec![0u32; field.radiance.len()];
        let mut slots: Vec<Vec<u32>> = spec.totals.iter().map(|t| vec![0; t.len()]).collect();
        for i in 0..catalog.len() as u32 {
            let counts = match catalog.part(i) {
                Part::Chunk(_) => &mut texels,
                Part::Tile { direction, .. } => &mut slots[direction as usize],
            };
            for c in &mut counts[catalog.range(i)] {
                *c += 1;
            }
            assert_eq!(catalog.index_of(catalog.part(i)), Some(i));
            assert_eq!(field.part_values(&catalog, i).len(), catalog.values(i));
        }
        assert!(texels.iter().all(|&c| c == 1));
        assert!(slots.iter().flatten().all(|&c| c == 1));
        let tiles = catalog
            .parts()
            .iter()
            .filter(|p| matches!(p, Part::Tile { .. }))
            .count();
        assert!(tiles > 0, "the mirror scene has tile parts");
        assert_eq!(
            catalog.total_values(),
            texels.len() + slots.iter().map(Vec::len).sum::<usize>()
        );
    }

    #[test]
    fn copying_every_part_rebuilds_the_field() {
        let field = field();
        let catalog = PartCatalog::new(&field);
        let mut empty = field.clone();
        empty.radiance.iter_mut().for_each(|v| *v = [0.0; 3]);
        if let Some(spec) = &mut empty.specular {
            spec.totals.iter_mut().flatten().for_each(|v| *v = [0.0; 3]);
        }
        assert_eq!(PartCatalog::new(&empty), catalog, "the catalog is geometry only");
        for i in 0..catalog.len() as u32 {
            empty
                .part_values_mut(&catalog, i)
                .copy_from_slice(field.part_values(&catalog, i));
        }
        assert_eq!(empty, field);
    }

    #[test]
    fn a_view_needs_diffuse_maps_first_then_its_heaviest_tiles() {
        let field = field();
        let catalog = PartCatalog::new(&field);
        let tiles: Vec<(u32, u32)> = catalog
            .parts()
            .iter()
            .filter_map(|p| match *p {
                Part::Tile { direction, tile } => Some((direction, tile)),
                Part::Chunk(_) => None,
            })
            .take(3)
            .collect();
        let mut needs = ViewNeeds::default();
        needs.surfaces.insert(2);
        for (&t, w) in tiles.iter().zip([0.5, 2.0, 1.0]) {
            needs.mirror_tiles.insert(t);
            needs.tile_weight.insert(t, w);
        }
        let tile = |(direction, tile)| Part::Tile { direction, tile };
        let order: Vec<Part> = catalog.needed(&needs).iter().map(|&i| catalog.part(i)).collect();
        assert_eq!(
            order,
            vec![
                Part::Chunk(catalog.chunk_of_surface(2)),
                tile(tiles[1]),
                tile(tiles[2]),
                tile(tiles[0])
            ]
        );
    }
}
