// Draws a light field: diffuse surfaces and emitters with their radiance maps, mirrors with
// their diffuse part plus what ray tracing through the static scene finds.
//
// Radiance maps. Every surface owns a rectangular grid of texels (see `vlf_core::maps`), one
// *part* of the field (`vlf_core::parts`); a part lies in the pool from `parts[part]` on, or is
// not resident (NONE, drawn black): texel (s, t) of surface i (its chart's grid) is
// `pool[parts[part_i] + texel_offset_i + t·width_i + s]`. A point
// reads its outgoing radiance bilinearly between texel centres, clamping at the grid's border,
// exactly as `LightField::radiance_at` does on the CPU. For the visible surface the texel
// coordinates (shifted by ½ to texel centres) come per vertex, computed in f64 on the CPU: they
// are affine on the polygon's plane, so perspective-correct interpolation reproduces them.
//
// Mirrors (`SpecularMode::Trace` of the CPU renderer). The eye ray is reflected at the mirror
// and traced through the scene's BVH (`vlf_core::render::bvh`, uploaded as it is: flat nodes in
// depth-first order, leaves listing surfaces); the diffuse radiance of what it meets is added,
// weighted by the product of the mirrors' ρs, up to `view.depth` mirrors deep. A back face or a
// miss ends the path with nothing.
//
// Mirrors from the rays (`SpecularMode::Rays`): see `mirror_from_rays`. While a tile they read is
// not resident (a viewer streaming the field), the mirror is ray traced instead, FALLBACK_DEPTH
// deep: the diffuse maps come first, so the reflection is right long before the tiles arrive.
//
// Exact direct light (`vlf_core::direct`), where `view.direct_parts` is not NONE: a diffuse point
// seen by the camera (or through a traced mirror) sends `L − D + ρd/π·E(p)`, with `D` the
// field's direct part read bilinearly from its chunk's *direct part* (part `view.direct_parts`
// + the chunk's number: more parts of the same pool) and `E(p)` summed over the emitters'
// quadrature points, one shadow ray each (`direct_irradiance`). See `crate::direct`.
//
// Back faces are drawn black: they still hide what lies behind them, as a back-face hit does for
// the CPU renderer's rays.
//
// Dynamic objects (objects.wgsl, appended to this file, with its own fragment entry point
// `fs_objects`): their triangles are drawn with the scene's, each of their fragments shaded by
// the gather, and the static scene's fragments lose the light the objects hide from them.
// Without objects this file alone is compiled: a smaller shader, quicker to build.

struct View {
    // VLF frame → clip space, sub-pixel jitter included.
    clip_from_vlf: mat4x4<f32>,
    // The eye in the VLF frame (w unused).
    eye: vec4<f32>,
    // Mirrors traced at most this deep; 0 draws mirrors without reflections.
    depth: u32,
    // How mirrors are drawn: 0 ray traced (`depth` deep), 1 from the field's rays.
    mode: u32,
    // Exact direct light: the part number of chunk 0's direct part, NONE when off.
    direct_parts: u32,
    _pad: u32,
};

struct Surface {
    normal: vec3<f32>,
    // Plane: normal · x = offset.
    offset: f32,
    specular: vec3<f32>,
    mirror: u32,
    grid_origin: vec3<f32>,
    inv_texel: f32,
    axis_u: vec3<f32>,
    // The part holding the surface's chart's diffuse map (a chunk of charts).
    part: u32,
    axis_v: vec3<f32>,
    width: u32,
    first_vertex: u32,
    vertex_count: u32,
    height: u32,
    // Index among the mirrors (for the ray tables), NONE for other surfaces.
    mirror_index: u32,
    // Where the surface's chart's texels start in its part (a chunk of charts).
    texel_offset: u32,
    // Diffuse reflectance: of the material (a texture's mean colour is not read), or of a
    // dynamic object's surface (those follow the static scene's, see objects.wgsl).
    diffuse: vec3<f32>,
};

struct Node {
    min_x: f32, min_y: f32, min_z: f32,
    max_x: f32, max_y: f32, max_z: f32,
    // Interior: the right child (the left one is the next node). Leaf: the first primitive.
    index: u32,
    // Primitives of a leaf; 0 marks an interior node.
    count: u32,
};

@group(0) @binding(0) var<uniform> view: View;
@group(0) @binding(1) var<storage, read> surfaces: array<Surface>;
// Resident radiance, RGB packed tightly (3 floats per texel or mirror slot), part by part.
@group(0) @binding(2) var<storage, read> pool: array<f32>;
// Polygon vertices (xyz, w unused), surface by surface.
@group(0) @binding(3) var<storage, read> vertices: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> nodes: array<Node>;
@group(0) @binding(5) var<storage, read> primitives: array<u32>;
// The look-up tables of the mirrors' directional radiance (see `rays.rs` for the layout).
@group(0) @binding(6) var<storage, read> rays: array<u32>;
// Per part: its first value in the pool, NONE while it is not resident.
@group(0) @binding(7) var<storage, read> parts: array<u32>;
// The emitters' quadrature points (`vlf_core::direct::Emitters`), two vec4 each: the point
// (xyz) and its power Le·A (rgb in the second's xyz), whose normal is its group's. Read by
// exact direct light and by the objects' shadows (objects.wgsl).
@group(0) @binding(11) var<storage, read> emitter_points: array<vec4<f32>>;
// Per emitting surface, four vec4: its centroid (xyz) and area (w); its normal (xyz) and
// index among the surfaces (w); its emission (xyz) and point count (w); its first point (x).
// Integers and floats share the vec4s, so they are stored as u32 (floats by their bits: read as
// f32, a small integer's bits would be a denormal, which a GPU may flush to zero). The buffer's
// zero padding reads as groups of no points.
@group(0) @binding(12) var<storage, read> emitter_groups: array<vec4<u32>>;

// Secondary rays start this far off the mirror and ignore hits closer than it (VLF frame, where
// the scene spans 2): f32 keeps about 10⁻⁷ there.
const RAY_EPSILON: f32 = 1e-5;
// A point at most this far outside a polygon's edge still hits it (VLF units).
const EDGE_EPSILON: f32 = 1e-6;
// Deeper than `vlf_core::render::bvh::MAX_DEPTH`: a traversal never overflows it.
const STACK_SIZE: u32 = 64u;
const NONE: u32 = 0xffffffffu;
// How deep a mirror is traced while the tiles of its rays are not resident.
const FALLBACK_DEPTH: u32 = 8u;
const PI: f32 = 3.14159265358979;
// Emitter points' shadow rays stop this much short of them (relative): more than the CPU's
// 10⁻⁶, which is below f32's error in where the ray meets the emitter it aims at.
const SHADOW_SHORTEN: f32 = 1e-4;
// Whether the pipeline draws exact direct light at all: set where it does, so that without it
// the driver drops the code (present but skipped, its loop cost a software rasteriser a
// quarter of its frame rate).
override EXACT_DIRECT: bool = false;

struct VertexIn {
    @location(0) position: vec3<f32>,
    @location(1) texel: vec2<f32>,
    @location(2) surface: u32,
};

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) texel: vec2<f32>,
    @location(1) @interpolate(flat) surface: u32,
    @location(2) position: vec3<f32>,
};

@vertex
fn vs_main(v: VertexIn) -> VertexOut {
    var out: VertexOut;
    out.clip = view.clip_from_vlf * vec4<f32>(v.position, 1.0);
    out.texel = v.texel;
    out.surface = v.surface;
    out.position = v.position;
    return out;
}

fn pool_rgb(value: u32) -> vec3<f32> {
    let i = value * 3u;
    return vec3<f32>(pool[i], pool[i + 1u], pool[i + 2u]);
}

// The four texels around texel coordinates `c` (already shifted by ½) of surface `s`, whose
// chart starts at pool value `base`: their values' places and bilinear weights, between texel
// centres and clamped at the grid's edges. Radiance and the objects' shadows (`objects.wgsl`)
// are looked up alike.
struct Taps {
    at: vec4<u32>,
    w: vec4<f32>,
};

fn taps(s: Surface, base: u32, c: vec2<f32>) -> Taps {
    let c0 = floor(c);
    let f = c - c0;
    let hi = vec2<f32>(f32(s.width - 1u), f32(s.height - 1u));
    let a = vec2<u32>(clamp(c0, vec2<f32>(0.0), hi));
    let b = vec2<u32>(clamp(c0 + 1.0, vec2<f32>(0.0), hi));
    let first = base + s.texel_offset;
    return Taps(
        vec4<u32>(first + a.y * s.width + a.x, first + a.y * s.width + b.x, first + b.y * s.width + a.x, first + b.y * s.width + b.x),
        vec4<f32>((1.0 - f.x) * (1.0 - f.y), f.x * (1.0 - f.y), (1.0 - f.x) * f.y, f.x * f.y),
    );
}

// Bilinear between texel centres at texel coordinates `c` (already shifted by ½); black while
// the surface's map is not resident.
fn bilinear(s: Surface, c: vec2<f32>) -> vec3<f32> {
    let base = parts[s.part];
    if (base == NONE) {
        return vec3<f32>(0.0);
    }
    return bilinear_at(s, base, c);
}

// Bilinear at `c` in the values of surface `s`'s chunk laid out from pool value `base` on.
fn bilinear_at(s: Surface, base: u32, c: vec2<f32>) -> vec3<f32> {
    let t = taps(s, base, c);
    return pool_rgb(t.at.x) * t.w.x + pool_rgb(t.at.y) * t.w.y + pool_rgb(t.at.z) * t.w.z + pool_rgb(t.at.w) * t.w.w;
}

// Texel coordinates (shifted by ½, as `bilinear` takes them) of point `p` of surface `s`.
fn texel_coords(s: Surface, p: vec3<f32>) -> vec2<f32> {
    let d = p - s.grid_origin;
    return vec2<f32>(dot(d, s.axis_u), dot(d, s.axis_v)) * s.inv_texel - 0.5;
}

// Diffuse radiance of surface `s` at point `p` (VLF frame).
fn diffuse_at(s: Surface, p: vec3<f32>) -> vec3<f32> {
    return bilinear(s, texel_coords(s, p));
}

// Entry distance of the ray into a node's box, or -1 when it misses it within [t_min, t_max].
fn slab(node: Node, o: vec3<f32>, inv: vec3<f32>, t_min: f32, t_max: f32) -> f32 {
    let a = (vec3<f32>(node.min_x, node.min_y, node.min_z) - o) * inv;
    let b = (vec3<f32>(node.max_x, node.max_y, node.max_z) - o) * inv;
    let lo = min(a, b);
    let hi = max(a, b);
    let near = max(max(lo.x, lo.y), max(lo.z, t_min));
    let far = min(min(hi.x, hi.y), min(hi.z, t_max));
    if (near <= far) {
        return near;
    }
    return -1.0;
}

struct Hit {
    surface: u32,
    t: f32,
    front: bool,
};

// The ray against convex polygon `index`: its `t` if hit within [t_min, t_max], else -1. Both
// faces are hit; the inside test is inclusive with EDGE_EPSILON, as on the CPU.
fn intersect_surface(index: u32, o: vec3<f32>, d: vec3<f32>, t_min: f32, t_max: f32) -> f32 {
    let s = surfaces[index];
    let denom = dot(s.normal, d);
    if (denom == 0.0 || s.vertex_count < 3u) {
        return -1.0;
    }
    let t = (s.offset - dot(s.normal, o)) / denom;
    if (!(t >= t_min && t <= t_max)) {
        return -1.0;
    }
    let p = o + t * d;
    var previous = vertices[s.first_vertex + s.vertex_count - 1u].xyz;
    for (var k = 0u; k < s.vertex_count; k++) {
        let vertex = vertices[s.first_vertex + k].xyz;
        let edge = vertex - previous;
        let c = dot(cross(edge, p - previous), s.normal);
        if (c < 0.0 && c * c > EDGE_EPSILON * EDGE_EPSILON * dot(edge, edge)) {
            return -1.0;
        }
        previous = vertex;
    }
    return t;
}

// The nearest static surface along `o + t·d`, t ≥ t_min (ties to the lowest index, as on the
// CPU).
fn trace(o: vec3<f32>, d: vec3<f32>, t_min: f32) -> Hit {
    // Only fragments of drawn polygons trace, so the scene has surfaces and the BVH a root.
    return trace_from(0u, o, d, t_min, 3.4e38);
}

// The nearest surface within [t_min, t_max] of the BVH whose root is node `root`: 0 for the
// static scene, the dynamic objects' root after it (their nodes follow the scene's, with
// indices into the same arrays).
fn trace_from(root: u32, o: vec3<f32>, d: vec3<f32>, t_min: f32, t_max: f32) -> Hit {
    return traverse(root, o, d, t_min, t_max, false);
}

// Whether a static surface lies on `o + t·d` within [0, t_max]: a shadow ray (the first hit
// found ends the traversal).
fn blocked(o: vec3<f32>, d: vec3<f32>, t_max: f32) -> bool {
    return traverse(0u, o, d, 0.0, t_max, true).surface != NONE;
}

// `trace_from`, or with `any_hit` the first hit found rather than the nearest.
fn traverse(root: u32, o: vec3<f32>, d: vec3<f32>, t_min: f32, t_max: f32, any_hit: bool) -> Hit {
    var best = Hit(NONE, t_max, false);
    // Components below 1e-30 become 1e-30, so the slab test never divides by zero (for a ray that
    // parallel to a slab, the sign of its huge inverse does not change the interval).
    let inv = 1.0 / select(d, vec3<f32>(1e-30), abs(d) < vec3<f32>(1e-30));
    var stack: array<u32, STACK_SIZE>;
    var top = 0u;
    if (slab(nodes[root], o, inv, t_min, best.t) < 0.0) {
        return best;
    }
    var current = root;
    loop {
        let node = nodes[current];
        var descended = false;
        if (node.count > 0u) {
            for (var k = 0u; k < node.count; k++) {
                let s = primitives[node.index + k];
                let t = intersect_surface(s, o, d, t_min, best.t);
                if (t >= 0.0 && (t < best.t || (t == best.t && s < best.surface))) {
                    best = Hit(s, t, dot(surfaces[s].normal, d) < 0.0);
                    if (any_hit) {
                        return best;
                    }
                }
            }
        } else {
            let left = current + 1u;
            let right = node.index;
            let tl = slab(nodes[left], o, inv, t_min, best.t);
            let tr = slab(nodes[right], o, inv, t_min, best.t);
            if (tl >= 0.0 && tr >= 0.0) {
                if (tl <= tr) {
                    stack[top] = right;
                    current = left;
                } else {
                    stack[top] = left;
                    current = right;
                }
                top = min(top + 1u, STACK_SIZE - 1u);
                descended = true;
            } else if (tl >= 0.0) {
                current = left;
                descended = true;
            } else if (tr >= 0.0) {
                current = right;
                descended = true;
            }
        }
        if (!descended) {
            // Pop the next node still worth visiting.
            var found = false;
            loop {
                if (top == 0u) {
                    break;
                }
                top -= 1u;
                if (slab(nodes[stack[top]], o, inv, t_min, best.t) >= 0.0) {
                    current = stack[top];
                    found = true;
                    break;
                }
            }
            if (!found) {
                break;
            }
        }
    }
    return best;
}


// ---- Mirrors from the rays (`LightField::mirror_radiance_from_rays`; tables in `rays.rs`) ----

fn ray_f32(i: u32) -> f32 {
    return bitcast<f32>(rays[i]);
}

fn ray_vec3(i: u32) -> vec3<f32> {
    return vec3<f32>(ray_f32(i), ray_f32(i + 1u), ray_f32(i + 2u));
}

// The unrotated unit vector of the lattice point (i, j) and its line direction's index.
fn lattice_point(i: i32, j: i32, n: i32) -> vec4<f32> {
    let o = rays[rays[4u] + u32((j + n) * (2 * n + 1) + (i + n))];
    let index = o & 0x7fffffffu;
    var v = ray_vec3(rays[5u] + 3u * index);
    if ((o >> 31u) != 0u) {
        v = -v;
    }
    return vec4<f32>(v, bitcast<f32>(index));
}

// The crossings of the ray of cell (x, y) of direction d with mirror planes, as a range of the
// crossings table (3 words each: the plane's first polygon, the part holding the ray, its index
// in the part); empty where no mirror crosses the ray's tile.
fn ray_crossings(d: u32, x: i32, y: i32) -> vec2<u32> {
    let resolution = i32(rays[3u]);
    if (x < 0 || y < 0 || x >= resolution || y >= resolution) {
        return vec2<u32>(0u);
    }
    let m = rays[10u];
    let per_side = rays[11u];
    let ux = u32(x);
    let uy = u32(y);
    let tile = rays[rays[7u] + d * per_side * per_side + (uy / m) * per_side + ux / m];
    if (tile == NONE) {
        return vec2<u32>(0u);
    }
    let c = rays[8u] + tile + (uy % m) * m + (ux % m);
    return vec2<u32>(rays[c], rays[c + 1u]);
}

// Where the ray of cell (x, y) of direction d stands for mirror `s` (`LightField::mirror_slot`):
// its part and its index in the part, or NONE. The ray's crossing of s's mirror plane if it has
// one; else the nearest crossing of a neighbouring mirror that faces the same side, has a normal
// within `NEIGHBOUR_ANGLE_COS` of s's and lies within `NEIGHBOUR_DEPTH_CELLS` ray spacings of s's
// plane along the ray (both in header words 12 and 13); ties go to the lower surface.
fn mirror_slot(d: u32, s: Surface, x: i32, y: i32) -> vec2<u32> {
    let range = ray_crossings(d, x, y);
    let table = rays[9u];
    for (var i = range.x; i < range.y; i++) {
        if (surfaces[rays[table + 3u * i]].mirror_index == s.mirror_index) {
            return vec2<u32>(rays[table + 3u * i + 1u], rays[table + 3u * i + 2u]);
        }
    }
    if (range.x == range.y) {
        return vec2<u32>(NONE);
    }
    // The ray's start (`PsfFrame::ray_origin` at the cell's centre) and direction w = u × v.
    let dir = rays[6u] + 8u * d;
    let u = ray_vec3(dir);
    let v = ray_vec3(dir + 3u);
    let w = cross(u, v);
    let step = 2.0 / f32(rays[3u]);
    let origin = u * ((f32(x) + 0.5 + ray_f32(dir + 6u)) * step - 1.0) + v * ((f32(y) + 0.5 + ray_f32(dir + 7u)) * step - 1.0);
    let side = dot(w, s.normal);
    let here = (s.offset - dot(s.normal, origin)) / side;
    var best = vec2<u32>(NONE);
    var best_distance = ray_f32(12u) * step;
    let least_cos = ray_f32(13u);
    var best_surface = NONE;
    for (var i = range.x; i < range.y; i++) {
        let other = rays[table + 3u * i];
        let q = surfaces[other];
        let facing = dot(q.normal, w);
        if (facing * side <= 0.0 || dot(q.normal, s.normal) < least_cos) {
            continue;
        }
        let distance = abs((q.offset - dot(q.normal, origin)) / facing - here);
        if (distance < best_distance || (distance == best_distance && other < best_surface)) {
            best = vec2<u32>(rays[table + 3u * i + 1u], rays[table + 3u * i + 2u]);
            best_distance = distance;
            best_surface = other;
        }
    }
    return best;
}

// Radiance leaving mirror `s` at `p` towards unit direction `outgoing`, from the maps; w is 1 when
// a ray it reads lies in a part that is not resident (the value is then incomplete).
fn mirror_from_rays(s: Surface, p: vec3<f32>, outgoing: vec3<f32>) -> vec4<f32> {
    // The spherical triangle of line directions around `outgoing` (`DirectionSet::triangle`).
    let rotation = mat3x3<f32>(ray_vec3(16u), ray_vec3(19u), ray_vec3(22u));
    var local = transpose(rotation) * outgoing;
    if (local.z < 0.0) {
        local = -local;
    }
    let n = i32(rays[0u]);
    let scale = f32(n) / (abs(local.x) + abs(local.y) + local.z);
    let px = local.x * scale;
    let py = local.y * scale;
    let sx = select(1, -1, px < 0.0);
    let sy = select(1, -1, py < 0.0);
    let a = abs(px);
    let b = abs(py);
    let fa = clamp(i32(floor(a)), 0, n - 1);
    let fb = clamp(i32(floor(b)), 0, n - 1 - fa);
    let upper = fa + fb < n - 1 && (a - f32(fa)) + (b - f32(fb)) > 1.0;
    var points: array<vec2<i32>, 3>;
    if (upper) {
        points = array<vec2<i32>, 3>(vec2<i32>(fa + 1, fb + 1), vec2<i32>(fa + 1, fb), vec2<i32>(fa, fb + 1));
    } else {
        points = array<vec2<i32>, 3>(vec2<i32>(fa, fb), vec2<i32>(fa + 1, fb), vec2<i32>(fa, fb + 1));
    }
    var v: array<vec3<f32>, 3>;
    var index: array<u32, 3>;
    for (var t = 0; t < 3; t++) {
        let q = lattice_point(sx * points[t].x, sy * points[t].y, n);
        v[t] = q.xyz;
        index[t] = bitcast<u32>(q.w);
    }
    let c23 = cross(v[1], v[2]);
    let c31 = cross(v[2], v[0]);
    let c12 = cross(v[0], v[1]);
    let det = dot(v[0], c23);
    var weights = max(vec3<f32>(dot(local, c23), dot(local, c31), dot(local, c12)) / det, vec3<f32>(0.0));
    let sum = weights.x + weights.y + weights.z;
    if (sum > 0.0) {
        weights = weights / sum;
    } else {
        let dots = vec3<f32>(dot(local, v[0]), dot(local, v[1]), dot(local, v[2]));
        if (dots.x >= dots.y && dots.x >= dots.z) {
            weights = vec3<f32>(1.0, 0.0, 0.0);
        } else if (dots.y >= dots.z) {
            weights = vec3<f32>(0.0, 1.0, 0.0);
        } else {
            weights = vec3<f32>(0.0, 0.0, 1.0);
        }
    }
    // In each direction's subfield: bilinear between the four rays around p's projection.
    let half_n = f32(rays[3u]) * 0.5;
    var out = vec3<f32>(0.0);
    var weight = 0.0;
    var missing = 0.0;
    for (var t = 0; t < 3; t++) {
        let bt = weights[t];
        if (bt <= 0.0) {
            continue;
        }
        let d = index[t];
        let dir = rays[6u] + 8u * d;
        let shift = vec2<f32>(ray_f32(dir + 6u), ray_f32(dir + 7u));
        let g = vec2<f32>((dot(p, ray_vec3(dir)) + 1.0) * half_n, (dot(p, ray_vec3(dir + 3u)) + 1.0) * half_n) - shift - 0.5;
        let g0 = floor(g);
        let f = g - g0;
        var value = vec3<f32>(0.0);
        var w_sum = 0.0;
        for (var k = 0; k < 4; k++) {
            let dx = k & 1;
            let dy = k >> 1u;
            let w = select(1.0 - f.x, f.x, dx == 1) * select(1.0 - f.y, f.y, dy == 1);
            let x = i32(g0.x) + dx;
            let y = i32(g0.y) + dy;
            if (w <= 0.0 || x < 0 || y < 0) {
                continue;
            }
            let slot = mirror_slot(d, s, x, y);
            if (slot.x != NONE) {
                let base = parts[slot.x];
                if (base == NONE) {
                    missing = 1.0;
                } else {
                    value += pool_rgb(base + slot.y) * w;
                    w_sum += w;
                }
            }
        }
        if (w_sum > 0.0) {
            out += value / w_sum * bt;
            weight += bt;
        }
    }
    if (weight > 0.0) {
        out /= weight;
    }
    return vec4<f32>(out, missing);
}

@fragment
fn fs_main(in: VertexOut, @builtin(front_facing) front: bool) -> @location(0) vec4<f32> {
    if (!front) {
        return vec4<f32>(0.0, 0.0, 0.0, 1.0);
    }
    let s = surfaces[in.surface];
    let diffuse = with_exact_direct(s, in.position, in.texel, bilinear(s, in.texel), NONE);
    let l = shade(s, in.position, normalize(in.position - view.eye.xyz), diffuse, view.mode, view.depth, true);
    return vec4<f32>(l, 1.0);
}

// ---- Exact direct light (`vlf_core::direct`) ----

// `E(p)`: the irradiance straight from the emitters at `p` on a surface of front normal `n`,
// Σ Le·A cos θ_p cos θ_s / r² over the quadrature points in front of it that no static surface
// hides (`Emitters::irradiance`), nor a dynamic object where `objects_root` is their BVH's root
// (`ExactDirect::irradiance_past`; NONE: none).
fn direct_irradiance(p: vec3<f32>, n: vec3<f32>, objects_root: u32) -> vec3<f32> {
    let origin = p + n * RAY_EPSILON;
    var e = vec3<f32>(0.0);
    for (var g = 0u; g < arrayLength(&emitter_groups) / 4u; g++) {
        let normal = bitcast<vec3<f32>>(emitter_groups[4u * g + 1u].xyz);
        let count = emitter_groups[4u * g + 2u].w;
        let first = emitter_groups[4u * g + 3u].x;
        for (var i = first; i < first + count; i++) {
            let to = emitter_points[2u * i].xyz - p;
            let r2 = dot(to, to);
            if (r2 <= 0.0) {
                continue;
            }
            let r = sqrt(r2);
            let w = to / r;
            let cos_p = dot(n, w);
            let cos_s = -dot(normal, w);
            let t_max = r * (1.0 - SHADOW_SHORTEN);
            if (cos_p <= 0.0 || cos_s <= 0.0 || blocked(origin, w, t_max)) {
                continue;
            }
            if (objects_root != NONE && traverse(objects_root, origin, w, 0.0, t_max, true).surface != NONE) {
                continue;
            }
            e += emitter_points[2u * i + 1u].xyz * (cos_p * cos_s / r2);
        }
    }
    return e;
}

// The diffuse radiance `l` of surface `s` at `p` (texel coordinates `c`, shifted by ½) with
// its direct part exact: `l − D + ρd/π·E(p)`, clamped at zero as on the CPU. `l` as it is
// where exact direct light is off, the surface reflects nothing, or its direct part is not
// resident (the field's own direct light then shows until it arrives). Shadow rays see the
// dynamic objects under `objects_root` (NONE: none).
fn with_exact_direct(s: Surface, p: vec3<f32>, c: vec2<f32>, l: vec3<f32>, objects_root: u32) -> vec3<f32> {
    if (!EXACT_DIRECT || view.direct_parts == NONE || !any(s.diffuse > vec3<f32>(0.0))) {
        return l;
    }
    let base = parts[view.direct_parts + s.part];
    if (base == NONE) {
        return l;
    }
    let d = bilinear_at(s, base, c);
    return max(l - d + s.diffuse / PI * direct_irradiance(p, s.normal, objects_root), vec3<f32>(0.0));
}

// The radiance the front of surface `s` sends from `p` back along the unit direction `d` it
// is seen along: `l`, its diffuse radiance, plus a mirror's reflection — from the field's rays
// (`mode` 1) or ray traced at most `depth` mirrors deep (`mode` 0), the diffuse surfaces it
// meets with exact direct light when `exact` (a camera's path; a gather reads the maps alone,
// as `LightField::shade_from_maps` does).
fn shade(first: Surface, position: vec3<f32>, incoming: vec3<f32>, diffuse: vec3<f32>, mode: u32, depth: u32, exact: bool) -> vec3<f32> {
    var s = first;
    var l = diffuse;
    if (s.mirror == 0u) {
        return l;
    }
    var remaining = depth;
    if (mode == 1u) {
        let m = mirror_from_rays(s, position, -incoming);
        if (m.w == 0.0) {
            return l + m.xyz;
        }
        remaining = FALLBACK_DEPTH;
    }
    if (remaining == 0u) {
        return l;
    }
    // Reflections: follow the eye ray from mirror to mirror.
    var weight = vec3<f32>(1.0);
    var p = position;
    var d = incoming;
    loop {
        weight *= s.specular;
        d = d - 2.0 * dot(d, s.normal) * s.normal;
        let origin = p + s.normal * RAY_EPSILON;
        let hit = trace(origin, d, RAY_EPSILON);
        if (hit.surface == NONE || !hit.front) {
            break;
        }
        p = origin + hit.t * d;
        s = surfaces[hit.surface];
        var seen = diffuse_at(s, p);
        if (exact) {
            seen = with_exact_direct(s, p, texel_coords(s, p), seen, NONE);
        }
        l += weight * seen;
        remaining -= 1u;
        if (s.mirror == 0u || remaining == 0u) {
            break;
        }
    }
    return l;
}
