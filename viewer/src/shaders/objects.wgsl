// Dynamic objects in a drawn field (appended to field.wgsl): what `vlf_core::dynamic` does on
// the CPU — the gather at an object's points (`gather.rs`), the shadows objects cast on the
// static scene (`shadow.rs`) and the objects seen in the static scene's mirrors (`view.rs`).
// The objects' surfaces follow the scene's in `surfaces` (from `objects.first_surface` on) and
// one BVH over all of them follows the scene's among `nodes` (root `objects.root`), so
// `trace_from` serves both. WGSL has no recursion: the static scene seen from an object is
// shaded by `shade` (field.wgsl), which knows nothing of objects.

struct Objects {
    // Surfaces from this index on are the objects'.
    first_surface: u32,
    // The objects' BVH root among `nodes`, NONE when there are none.
    root: u32,
    count: u32,
    // Line directions of the gather (`gather_directions`).
    directions: u32,
    // Cells of each object's shadow cone (K); 0 casts no shadows.
    shadow_cells: u32,
    // Emitting surfaces (`emitter_groups`).
    emitter_groups: u32,
    // 1: static surfaces read their shadow from `shadow_pool` (computed per texel by
    // `shadow_texels.wgsl` when the objects move); 0: computed per fragment.
    shadow_texels: u32,
    // 1: gather rays read the static surfaces less the objects' shadows per texel
    // (`Gatherer::with_gather_shadows`).
    gather_shadows: u32,
    // 1: shadows give back the light the objects reflect (`object_light`,
    // `Gatherer::with_bounce_light`).
    bounce_light: u32,
    // With exact direct light and shadows per texel: where in `shadow_pool` the camera's
    // shadows start (in floats; 0: none). They leave direct light to the shadow rays, where the
    // gather's, from 0 on, hold it (the gather reads the maps).
    camera_shadows: u32,
    _pad1: u32,
    _pad2: u32,
};

@group(0) @binding(8) var<uniform> objects: Objects;
// Per object: the centre (xyz) and radius (w) of a sphere holding it.
@group(0) @binding(9) var<storage, read> spheres: array<vec4<f32>>;
// Per line direction of the gather: its unit vector (xyz) and weight Δω (w).
@group(0) @binding(10) var<storage, read> gather_directions: array<vec4<f32>>;
// Per value of the radiance pool: the radiance its texel loses to the objects (RGB, three
// floats), when `objects.shadow_texels` is set. Written by `shadow_texels_main`, read here.
@group(0) @binding(13) var<storage, read_write> shadow_pool: array<f32>;
// Per object surface (from `objects.first_surface` on): the diffuse radiance it sends (RGB,
// three floats), gathered at its centroid by `object_light_main` (shadow_texels.wgsl).
@group(0) @binding(14) var<storage, read_write> object_light: array<f32>;

const GOLDEN_ANGLE: f32 = 2.39996322972865;

// The nearest object along `o + t·d` before t_max (NONE when none).
fn nearest_object(o: vec3<f32>, d: vec3<f32>, t_max: f32) -> Hit {
    if (objects.root == NONE) {
        return Hit(NONE, t_max, false);
    }
    return trace_from(objects.root, o, d, 0.0, t_max);
}

// Radiance arriving at `o` from −d (xyz): the static surface's (shaded as the field holds it),
// or nothing where an object is nearer or nothing is hit; with exact direct light and not
// `keep_emission`, less the surface's own emission (the shadow rays of `gathered_direct` count
// it for a gather ray; a mirror's reflected ray has no shadow rays, so it keeps the emitter's
// light, as `Gatherer::arriving` does). w is 0 where the surface's radiance map is not resident
// (a streaming view): the gather leaves such directions out of its mean until they arrive, so
// that an object is lit by the light known so far rather than drawn darker.
fn arriving(o: vec3<f32>, d: vec3<f32>, mode: u32, depth: u32, keep_emission: bool) -> vec4<f32> {
    let hit = trace_from(0u, o, d, 0.0, 3.4e38);
    if (hit.surface == NONE || !hit.front || nearest_object(o, d, hit.t).surface != NONE) {
        return vec4<f32>(0.0, 0.0, 0.0, 1.0);
    }
    let s = surfaces[hit.surface];
    let p = o + hit.t * d;
    let known = select(0.0, 1.0, parts[s.part] != NONE);
    var diffuse = diffuse_at(s, p);
    if (objects.gather_shadows != 0u) {
        diffuse = max(diffuse - shadow_from_texels(s, p, 0u), vec3<f32>(0.0));
    }
    var l = shade(s, p, d, diffuse, mode, depth, false);
    if (EXACT_DIRECT && !keep_emission) {
        let eg = emitter_group(hit.surface);
        if (eg != NONE) {
            l = max(l - bitcast<vec3<f32>>(emitter_groups[4u * eg + 2u].xyz), vec3<f32>(0.0));
        }
    }
    return vec4<f32>(l, known);
}

// What exact direct light adds to the gather's mean at `p` (normal `n`): `E(p)/π`, its shadow
// rays stopped by the objects too (`Gatherer::incident`); nothing without it.
fn gathered_direct(p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    if (!EXACT_DIRECT) {
        return vec3<f32>(0.0);
    }
    return direct_irradiance(p, n, objects.root) / PI;
}

// The cosine-weighted mean radiance arriving at `p` over the hemisphere of unit `n`, over the
// gather's directions (`Gatherer::incident`).
fn incident(p: vec3<f32>, n: vec3<f32>, mode: u32, depth: u32) -> vec3<f32> {
    let origin = p + n * RAY_EPSILON;
    var sum = vec3<f32>(0.0);
    var weights = 0.0;
    for (var k = 0u; k < objects.directions; k++) {
        let direction = gather_directions[k];
        let c = dot(n, direction.xyz);
        if (c == 0.0) {
            continue;
        }
        let d = select(-direction.xyz, direction.xyz, c > 0.0);
        let w = abs(c) * direction.w;
        let l = arriving(origin, d, mode, depth, false);
        weights += w * l.w;
        sum += l.xyz * (w * l.w);
    }
    if (weights > 0.0) {
        sum /= weights;
    }
    return sum + gathered_direct(p, n);
}

// Radiance the front of object surface `index` sends from `p` back along `incoming`: ρd times
// the gathered light (`incident`), plus, when `mirrored`, ρs times what the reflected ray
// meets in the static scene as the maps hold it, emission included (`Gatherer::arriving`: the
// CPU's reflection of an object mirror from the rays, or at the end of a traced path). A
// traced path that goes on past the object's mirror (`radiance_among_objects`) leaves the
// reflection out. One loop over the gather's directions and then the reflected ray, so that
// the shader holds one copy of `arriving` here (every call site of a function is a copy of it
// once the driver inlines it, and a large shader takes long to build).
fn object_radiance(index: u32, p: vec3<f32>, incoming: vec3<f32>, mode: u32, depth: u32, mirrored_too: bool) -> vec3<f32> {
    let s = surfaces[index];
    let n = s.normal;
    let origin = p + n * RAY_EPSILON;
    let count = select(0u, objects.directions, any(s.diffuse > vec3<f32>(0.0)));
    var sum = vec3<f32>(0.0);
    var weights = 0.0;
    var mirrored = vec3<f32>(0.0);
    for (var k = 0u; k <= count; k++) {
        var d = incoming - 2.0 * dot(incoming, n) * n;
        var w = 0.0;
        if (k < count) {
            let direction = gather_directions[k];
            let c = dot(n, direction.xyz);
            if (c == 0.0) {
                continue;
            }
            d = select(-direction.xyz, direction.xyz, c > 0.0);
            w = abs(c) * direction.w;
        } else if (s.mirror == 0u || !mirrored_too) {
            break;
        }
        // The reflected ray (k == count) keeps the emitters' emission: no shadow ray counts it.
        let l = arriving(origin, d, mode, depth, k == count);
        if (k < count) {
            sum += l.xyz * (w * l.w);
            weights += w * l.w;
        } else {
            mirrored = l.xyz;
        }
    }
    var gathered = gathered_direct(p, n);
    if (weights > 0.0) {
        gathered += sum / weights;
    }
    return s.specular * mirrored + s.diffuse * gathered;
}

// ---- Shadows (`vlf_core::dynamic::shadow`) ----

// `glam`'s `any_orthonormal_pair` (Duff et al.), so the cells fall where the CPU's do.
fn orthonormal_u(v: vec3<f32>) -> vec3<f32> {
    let sign = select(-1.0, 1.0, v.z >= 0.0);
    let a = -1.0 / (sign + v.z);
    return vec3<f32>(1.0 + sign * v.x * v.x * a, sign * v.x * v.y * a, -sign * v.x);
}

fn orthonormal_v(v: vec3<f32>) -> vec3<f32> {
    let sign = select(-1.0, 1.0, v.z >= 0.0);
    let a = -1.0 / (sign + v.z);
    return vec3<f32>(v.x * v.y * a, sign + v.y * v.y * a, -v.y);
}

// The cone from `o` toward object j's sphere: its axis (xyz) and cos α (w; −1 inside).
fn cone(o: vec3<f32>, j: u32) -> vec4<f32> {
    let sphere = spheres[j];
    let to = sphere.xyz - o;
    let d = length(to);
    if (d <= sphere.w || d == 0.0) {
        return vec4<f32>(select(vec3<f32>(0.0, 0.0, 1.0), to / d, d > 0.0), -1.0);
    }
    let sine = sphere.w / d;
    return vec4<f32>(to / d, sqrt(1.0 - sine * sine));
}

fn reaches_above(c: vec4<f32>, n: vec3<f32>) -> bool {
    if (c.w <= 0.0) {
        return true;
    }
    return dot(n, c.xyz) > -sqrt(1.0 - c.w * c.w);
}

fn cone_solid_angle(c: vec4<f32>) -> f32 {
    return 2.0 * PI * (1.0 - c.w);
}

// Whether emitter group `g`'s direct light is counted on the cone's cells at `p` (its points
// are farther apart than the cells, `cell` sr each), not on its points.
fn on_cells(g: u32, p: vec3<f32>, cell: f32) -> bool {
    let a = bitcast<vec4<f32>>(emitter_groups[4u * g]);
    let normal = bitcast<vec3<f32>>(emitter_groups[4u * g + 1u].xyz);
    let count = emitter_groups[4u * g + 2u].w;
    let to = p - a.xyz;
    let r = length(to);
    let solid_angle = min(a.w * max(dot(normal, to), 0.0) / (r * r * r), 2.0 * PI);
    return solid_angle / f32(count) > cell;
}

// The group of emitting surface `surface`, NONE for a surface that does not emit.
fn emitter_group(surface: u32) -> u32 {
    for (var g = 0u; g < objects.emitter_groups; g++) {
        if (emitter_groups[4u * g + 1u].w == surface) {
            return g;
        }
    }
    return NONE;
}

// The radiance a static diffuse point at `p` (normal `n`, reflectance `rho`) loses to the
// objects (`Gatherer::shadow_loss`); w is 1 when any object takes light from it. The cones'
// cells and the emitters' points are visited by one loop (cells first), each a ray traced once
// through the objects and once through the scene. Without `direct`, direct light is left to
// exact direct light's shadow rays: no emitter's points, and every emitter's emission left out
// of the cells (`Gatherer::diffuse_with_shadows`).
fn shadow_loss(p: vec3<f32>, n: vec3<f32>, rho: vec3<f32>, mode: u32, depth: u32, bounce: bool, direct: bool) -> vec4<f32> {
    let k = objects.shadow_cells;
    if (k == 0u || objects.count == 0u || !any(rho > vec3<f32>(0.0))) {
        return vec4<f32>(0.0);
    }
    let origin = p + n * RAY_EPSILON;
    var above = false;
    var cell_max = 0.0;
    for (var j = 0u; j < objects.count; j++) {
        let c = cone(origin, j);
        above = above || reaches_above(c, n);
        cell_max = max(cell_max, cone_solid_angle(c) / f32(k));
    }
    if (!above) {
        return vec4<f32>(0.0);
    }
    var lost = vec3<f32>(0.0);
    var hit_any = false;
    // The cursor: cell i of object j's cone, then point i of emitter group g.
    var j = 0u;
    var g = 0u;
    var i = 0u;
    loop {
        var w: vec3<f32>;
        var weight = 0.0;
        var t_max = 3.4e38;
        var power = vec3<f32>(0.0);
        let on_cone = j < objects.count;
        if (on_cone) {
            let c = cone(origin, j);
            if (i >= k || !reaches_above(c, n)) {
                j += 1u;
                i = 0u;
                continue;
            }
            let cos_theta = 1.0 - (1.0 - c.w) * (f32(i) + 0.5) / f32(k);
            let sin_theta = sqrt(max(1.0 - cos_theta * cos_theta, 0.0));
            let phi = f32(i) * GOLDEN_ANGLE;
            i += 1u;
            w = normalize(orthonormal_u(c.xyz) * (cos(phi) * sin_theta) + orthonormal_v(c.xyz) * (sin(phi) * sin_theta) + c.xyz * cos_theta);
            weight = dot(n, w) * cone_solid_angle(c) / f32(k);
            if (weight <= 0.0) {
                continue;
            }
            var earlier = false;
            for (var e = 0u; e < j; e++) {
                let ce = cone(origin, e);
                earlier = earlier || dot(w, ce.xyz) >= ce.w;
            }
            if (earlier) {
                continue;
            }
        } else {
            if (!direct || g >= objects.emitter_groups) {
                break;
            }
            let count = emitter_groups[4u * g + 2u].w;
            if (i >= count || on_cells(g, p, cell_max)) {
                g += 1u;
                i = 0u;
                continue;
            }
            let point = emitter_points[2u * (emitter_groups[4u * g + 3u].x + i)].xyz;
            power = emitter_points[2u * (emitter_groups[4u * g + 3u].x + i) + 1u].xyz;
            i += 1u;
            let to = point - p;
            let r2 = dot(to, to);
            if (r2 <= 0.0) {
                continue;
            }
            let r = sqrt(r2);
            w = to / r;
            let cos_p = dot(n, w);
            let cos_s = -dot(bitcast<vec3<f32>>(emitter_groups[4u * g + 1u].xyz), w);
            if (cos_p <= 0.0 || cos_s <= 0.0) {
                continue;
            }
            power *= cos_p * cos_s / r2;
            t_max = r * (1.0 - SHADOW_SHORTEN);
        }
        // An object in the way, and no static surface before it (a cell) or at all (an
        // emitter's point).
        let blocker = nearest_object(origin, w, t_max);
        if (blocker.surface == NONE) {
            continue;
        }
        let hit = trace_from(0u, origin, w, 0.0, t_max);
        if (hit.surface != NONE && (!on_cone || hit.t < blocker.t)) {
            continue;
        }
        hit_any = true;
        if (!on_cone) {
            lost += power;
            continue;
        }
        // The object's own light, given back.
        if (bounce && blocker.front) {
            let o = 3u * (blocker.surface - objects.first_surface);
            lost -= vec3<f32>(object_light[o], object_light[o + 1u], object_light[o + 2u]) * weight;
        }
        // The static surface behind the object: what it sends back, its emission left out
        // where its direct light is counted on its points.
        if (hit.surface == NONE || !hit.front) {
            continue;
        }
        let s = surfaces[hit.surface];
        let q = origin + hit.t * w;
        var l = shade(s, q, w, diffuse_at(s, q), mode, depth, false);
        let eg = emitter_group(hit.surface);
        if (eg != NONE && (!direct || !on_cells(eg, p, cell_max))) {
            l = max(l - bitcast<vec3<f32>>(emitter_groups[4u * eg + 2u].xyz), vec3<f32>(0.0));
        }
        lost += l * weight;
    }
    if (!hit_any) {
        return vec4<f32>(0.0);
    }
    return vec4<f32>(rho / PI * lost, 1.0);
}

// The objects' shadow at `p` on static surface `s` from the texels' (`shadow_pool`), bilinear
// between texel centres as its radiance is (`bilinear`); none while its map is not resident.
// `start`: the float where the shadows read start (0, or `objects.camera_shadows`).
fn shadow_from_texels(s: Surface, p: vec3<f32>, start: u32) -> vec3<f32> {
    let base = parts[s.part];
    if (base == NONE) {
        return vec3<f32>(0.0);
    }
    let t = taps(s, base, texel_coords(s, p));
    return shadow_rgb(t.at.x, start) * t.w.x + shadow_rgb(t.at.y, start) * t.w.y + shadow_rgb(t.at.z, start) * t.w.z
        + shadow_rgb(t.at.w, start) * t.w.w;
}

fn shadow_rgb(value: u32, start: u32) -> vec3<f32> {
    let i = start + value * 3u;
    return vec3<f32>(shadow_pool[i], shadow_pool[i + 1u], shadow_pool[i + 2u]);
}

// ---- A view with objects (`vlf_core::dynamic::view`) ----

// What a camera ray sees with the objects in the scene, from the fragment of surface `start`
// at `position` (its radiance map read at `diffuse`) on: an object is shaded by the gather; a
// static surface sends its diffuse radiance less the objects' shadow, and a mirror adds what
// its reflection meets — traced at most `depth` mirrors deep (`mode` 0), or read from the
// field's rays (`mode` 1), whose reflected ray is traced once to find an object, or an
// object's shadow, in the way. A mirror whose tiles of the rays are not resident (a streaming
// view) is traced instead, FALLBACK_DEPTH deep, as `shade` does. Traced, an object's mirror
// goes on along the path like a static one (`render_with_objects` on the CPU); read from the
// rays, or at the end of the depth, it shows the static scene as the maps hold it. One loop
// along the path, so that the gather and the shadow each have one call site.
fn radiance_among_objects(start: u32, position: vec3<f32>, incoming: vec3<f32>, diffuse: vec3<f32>, mode: u32, depth: u32) -> vec3<f32> {
    var l = vec3<f32>(0.0);
    // What the current surface's light counts for (the mirrors' ρs so far).
    var weight = vec3<f32>(1.0);
    var index = start;
    var p = position;
    var d = incoming;
    // The static surface's radiance before its shadow, and how much of the shadow it loses.
    var base = diffuse;
    var scale = vec3<f32>(1.0);
    // Where the shadow is taken: at the surface itself, or (mirrors from the rays) at the
    // static point its reflected ray meets; NONE for no shadow.
    var shadow_surface = start;
    var shadow_point = position;
    // Whether mirrors are traced (mode 0, or tiles missing), and how many reflections are left:
    // the CPU's `depth` at this point of its recursion.
    var traced = mode == 0u;
    var remaining = depth;
    var last = false;
    loop {
        if (index >= objects.first_surface) {
            let onward = traced && remaining > 0u && surfaces[index].mirror != 0u;
            l += weight * object_radiance(index, p, d, mode, depth, !onward);
            if (!onward) {
                break;
            }
        } else {
            var value = base;
            if (shadow_surface != NONE) {
                let q = surfaces[shadow_surface];
                var loss: vec4<f32>;
                // A point seen (or traced to) has exact direct light's shadow rays see the
                // objects; one read from a mirror's rays has the field's direct light.
                let direct = !EXACT_DIRECT || last;
                if (objects.shadow_texels != 0u) {
                    let texels = shadow_from_texels(q, shadow_point, select(objects.camera_shadows, 0u, direct));
                    loss = vec4<f32>(texels, select(0.0, 1.0, any(texels != vec3<f32>(0.0))));
                } else {
                    loss = shadow_loss(shadow_point, q.normal, q.diffuse, mode, depth, objects.bounce_light != 0u, direct);
                }
                if (loss.w != 0.0) {
                    value = max(base - scale * loss.xyz, vec3<f32>(0.0));
                }
            }
            l += weight * value;
            if (last || surfaces[index].mirror == 0u || (traced && remaining == 0u)) {
                break;
            }
        }
        let s = surfaces[index];
        let reflected = d - 2.0 * dot(d, s.normal) * s.normal;
        let origin = p + s.normal * RAY_EPSILON;
        let hit = trace_from(0u, origin, reflected, select(RAY_EPSILON, 0.0, !traced), 3.4e38);
        let object = nearest_object(origin, reflected, hit.t);
        if (object.surface != NONE) {
            if (!object.front) {
                break;
            }
            // The object is what the mirror shows.
            weight *= s.specular;
            if (traced) {
                remaining -= 1u;
            }
            index = object.surface;
            p = origin + object.t * reflected;
            d = reflected;
            continue;
        }
        if (!traced) {
            let m = mirror_from_rays(s, p, -d);
            if (m.w == 0.0) {
                // From the rays, less the shadow of the static point the reflection meets.
                base = m.xyz;
                scale = s.specular;
                shadow_surface = select(NONE, hit.surface, hit.surface != NONE && hit.front);
                shadow_point = origin + hit.t * reflected;
                last = true;
                continue;
            }
            // The view's tiles are not resident: traced through the maps that are.
            traced = true;
            remaining = FALLBACK_DEPTH;
        }
        if (hit.surface == NONE || !hit.front) {
            break;
        }
        weight *= s.specular;
        remaining -= 1u;
        index = hit.surface;
        p = origin + hit.t * reflected;
        d = reflected;
        base = with_exact_direct(surfaces[index], p, texel_coords(surfaces[index], p), diffuse_at(surfaces[index], p), objects.root);
        scale = vec3<f32>(1.0);
        shadow_surface = index;
        shadow_point = p;
    }
    return l;
}

@fragment
fn fs_objects(in: VertexOut, @builtin(front_facing) front: bool) -> @location(0) vec4<f32> {
    if (!front) {
        return vec4<f32>(0.0, 0.0, 0.0, 1.0);
    }
    var diffuse = vec3<f32>(0.0);
    if (in.surface < objects.first_surface) {
        let s = surfaces[in.surface];
        diffuse = with_exact_direct(s, in.position, in.texel, bilinear(s, in.texel), objects.root);
    }
    let incoming = normalize(in.position - view.eye.xyz);
    return vec4<f32>(radiance_among_objects(in.surface, in.position, incoming, diffuse, view.mode, view.depth), 1.0);
}
