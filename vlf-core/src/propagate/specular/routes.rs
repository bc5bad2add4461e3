//! The reflection routes: along which directions the light that one direction brings to a
//! mirror leaves it, and with what share (the module docs of [`super`]).

use super::MirrorView;
use crate::directions::DirectionSet;
use crate::scene::Scene;
use glam::DVec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// One feed of a target direction: light arriving on `mirror` along source
/// line direction `source` reflects into the target with share `weight`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Route {
    pub mirror: u32,
    pub source: u32,
    pub weight: f64,
}

/// The routes into every direction of `directions` (`routes[i]`: what feeds target `i`, sorted
/// by (mirror, source)) from the mirrors `mirrors` (`ordinal`: each one's, by surface) as the
/// directions' `views` cross them.
pub(super) fn find(
    scene: &Scene,
    directions: &DirectionSet,
    mirrors: &[u32],
    ordinal: &[u32],
    views: &[MirrorView],
) -> Vec<Vec<Route>> {
    // crossing[k]: the directions (increasing) whose rays meet mirror k, an entry of its
    // in their layout; listed per mirror, as the routes ask, and only where they meet.
    let mut crossing: Vec<Vec<u32>> = vec![Vec::new(); mirrors.len()];
    for (d, view) in views.iter().enumerate() {
        for &(s, _, _) in &view.layout.entries {
            let list = &mut crossing[ordinal[s as usize] as usize];
            if list.last() != Some(&(d as u32)) {
                list.push(d as u32);
            }
        }
    }
    let per_mirror: Vec<Vec<(u32, Route)>> = mirrors
        .par_iter()
        .zip(&crossing)
        .map(|(&m, crossing)| mirror_routes(scene, directions, crossing, m))
        .collect();
    drop(crossing);
    let mut routes = vec![Vec::new(); directions.len()];
    for list in per_mirror {
        for (target, route) in list {
            routes[target as usize].push(route);
        }
    }
    routes
        .par_iter_mut()
        .for_each(|r| r.sort_by_key(|r| (r.mirror, r.source)));
    routes
}

/// The routes of mirror `m`: for every source line direction whose rays cross it (`crossing`,
/// increasing), where its reflection goes, as (target, route).
fn mirror_routes(scene: &Scene, directions: &DirectionSet, crossing: &[u32], m: u32) -> Vec<(u32, Route)> {
    let n = scene.surfaces[m as usize].normal;
    let crosses = |d: u32| crossing.binary_search(&d).is_ok();
    // The grazing fallback's candidates, the crossing line directions not parallel to the
    // mirror, gathered once per mirror rather than once per source (a curved mirror's many small
    // planes fall back often, and this scan was most of the routes' time).
    let candidates: Vec<(u32, DVec3)> = (crossing.iter())
        .map(|&t| (t, directions.get(t as usize).vector))
        .filter(|(_, v)| v.dot(n).abs() > 1e-9)
        .collect();
    let mut out = Vec::new();
    for &source in crossing {
        let w = directions.get(source as usize).vector;
        let c = w.dot(n);
        // The orientation of the line that travels towards the front side.
        let incoming = if c < 0.0 { w } else { -w };
        let r = incoming - 2.0 * incoming.dot(n) * n;
        let tri = directions.triangle(r);
        // Keep vertices that leave the front side and whose rays cross the mirror.
        let mut kept: Vec<(u32, f64)> = tri
            .vertices
            .iter()
            .zip(tri.weights)
            .filter(|(o, b)| *b > 0.0 && directions.vector(**o).dot(n) > 1e-9 && crosses(o.index))
            .map(|(o, b)| (o.index, b))
            .collect();
        if kept.is_empty() {
            // Grazing reflection whose triangle lies behind the mirror or misses
            // it: the closest line direction that does leave the front (the largest |t·r|,
            // the lowest index of equals: candidates are in increasing index).
            let mut best: Option<(u32, f64)> = None;
            for &(t, v) in &candidates {
                let f = v.dot(r).abs();
                if best.is_none_or(|(_, b)| f.total_cmp(&b).is_gt()) {
                    best = Some((t, f));
                }
            }
            match best {
                Some((t, _)) => kept.push((t, 1.0)),
                None => continue,
            }
        }
        let total: f64 = kept.iter().map(|(_, b)| b).sum();
        for (target, b) in kept {
            out.push((
                target,
                Route {
                    mirror: m,
                    source,
                    weight: b / total,
                },
            ));
        }
    }
    out
}
