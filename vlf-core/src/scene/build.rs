//! From polygons to a [`Scene`]: the validation, splitting and normalisation
//! shared by every importer ([`load_obj`](super::load_obj),
//! [`load_gltf`](super::load_gltf)) and by programmatic scenes
//! ([`Scene::from_polygons`]). A format's module only reads its file into
//! polygons (vertices in scene units, counter-clockwise about the front, a
//! material index, a [`FaceOrigin`]) and [`Material`]s; everything the VLF
//! method relies on is checked once, here.
//!
//! # Conventions
//!
//! * **Faces are one-sided.** The front is the side from which the vertices
//!   run counter-clockwise (right-hand rule); only the front emits and
//!   reflects. Every [`Surface`] is planar, convex and counter-clockwise
//!   about its `normal`, because the propagation rasterises a surface into
//!   each ray row of a subfield as a single span.
//! * **Planar faces** (every vertex within
//!   [`ImportOptions::planarity_tolerance`] × the face's diameter of the
//!   face's Newell plane) are flattened onto that plane (moving vertices by
//!   at most the tolerance), so that `normal · x = offset` holds for every
//!   vertex; convex ones are kept whole, non-convex ones are split into
//!   convex pieces (ear clipping, then merged back while convex). A triangle
//!   is planar by construction and is never moved: its vertices stay
//!   bit-exact, so edges it shares with its neighbours stay shared.
//! * **Non-planar faces** (beyond the tolerance) are *triangulated on their
//!   own vertices*, not refused: real exports are full of slightly bent
//!   quads (a measured Cornell box has one bent by 1e-3 of its diameter), and
//!   flattening such a face would move its vertices off the edges it shares
//!   with its neighbours, opening cracks that light leaks through. The split
//!   is made in the projection onto the face's Newell plane (a quad along
//!   its shorter valid diagonal, which gives the better-conditioned
//!   triangles; a larger face by ear clipping, so non-convex faces work),
//!   and each triangle is then an ordinary planar face. A warning names the
//!   face and its deviation. A face whose projection intersects itself is
//!   still an error.
//! * **Degenerate faces** (zero area, e.g. collinear or repeated vertices,
//!   and zero-area triangles of a split) are not errors, since exporters
//!   produce them routinely: they are skipped, with a warning returned
//!   alongside the scene and logged with `tracing::warn!`.
//! * **Materials** must be physical: ρd, ρs in `[0, 1]`, ρd + ρs ≤ 1 per
//!   channel, emitted radiance finite and ≥ 0. A mirror reflectance above
//!   [`MAX_MIRROR_REFLECTANCE`] is capped (with a warning). The scene needs
//!   at least one face, and at least one face of an emitting material.
//! * **Normalisation into the VLF frame.** `x_vlf = (x - center) × scale`
//!   where `center` is the centre of the bounding box and `scale` maps the
//!   vertex farthest from it onto [`Scene::FRAME_RADIUS`]. Computed in f64
//!   throughout.
//!
//! Errors and warnings name the source file, and the line where the format
//! has lines (a [`FaceOrigin::line`] of 0 means none).

use glam::DVec3;

use super::bent::triangulate;
use super::polygon::{
    PolygonError, REL_AREA_EPS, centroid, convex_pieces, diameter, newell_normal, planarity_deviation,
};
use super::{FaceOrigin, Material, Normalisation, Rgb, Scene, Surface, Texture, UvMap};
use crate::Error;

/// Options of the importers.
#[derive(Clone, Debug)]
pub struct ImportOptions {
    /// The threshold between flattening and triangulating a face: the
    /// largest distance of a vertex from the face's Newell plane, relative to
    /// the face's diameter, for which the face is flattened onto that plane
    /// and kept whole (default `1e-3`). Exporters write coordinates with few
    /// digits, so exact planarity cannot be asked; a face bent further has no
    /// single normal and is split into triangles on its own vertices instead
    /// (with a warning), since flattening it would move its vertices
    /// visibly. `0` triangulates every face with four or more vertices that
    /// is not exactly planar.
    pub planarity_tolerance: f64,
    /// Read no file outside the scene file's folder: an OBJ's `mtllib` must then name a plain
    /// file beside it (glTF's buffers and images always must). A server importing an upload
    /// sets it, so an upload cannot make it read its own files.
    pub confined: bool,
    /// Import a dynamic object ([`crate::dynamic`]) rather than a scene: it needs no emitter
    /// (it is lit by a field), so a file without one is not refused.
    pub object: bool,
}

impl ImportOptions {
    /// Default of [`ImportOptions::planarity_tolerance`].
    pub const DEFAULT_PLANARITY_TOLERANCE: f64 = 1e-3;
}

impl Default for ImportOptions {
    fn default() -> Self {
        ImportOptions {
            planarity_tolerance: Self::DEFAULT_PLANARITY_TOLERANCE,
            confined: false,
            object: false,
        }
    }
}

/// A convex planar piece of an input face, in scene units.
struct Piece {
    vertices: Vec<DVec3>,
    normal: DVec3,
    material: usize,
    origin: FaceOrigin,
    /// The input face's texture coordinates (affine over its plane, so every piece shares them).
    uv: Option<UvMap>,
}

/// Albedo textures of a format that has them (glTF): the textures its materials name, and
/// the texture coordinates of each input polygon (empty: none).
#[derive(Default)]
pub(crate) struct Textured {
    pub textures: Vec<Texture>,
    pub uvs: Vec<Option<UvMap>>,
}

/// A scene's warnings as an importer gathers them: the first [`MAX_LISTED_WARNINGS`] listed (and
/// logged), the rest counted. A warning the same as the one before it (the two sides of a
/// double-sided face) is said once.
#[derive(Default)]
pub(crate) struct Warnings {
    listed: Vec<String>,
    unlisted: usize,
    last: String,
}

impl Warnings {
    pub(crate) fn push(&mut self, msg: String) {
        if msg == self.last {
            return;
        }
        if self.listed.len() < MAX_LISTED_WARNINGS {
            tracing::warn!("{msg}");
            self.listed.push(msg.clone());
        } else {
            self.unlisted += 1;
        }
        self.last = msg;
    }

    /// The warnings listed, and one more that counts the others, if any.
    pub(crate) fn into_list(self, file: &str) -> Vec<String> {
        let mut listed = self.listed;
        if self.unlisted > 0 {
            let msg = format!("{file}: {} more warnings like those above (not listed)", self.unlisted);
            tracing::warn!("{msg}");
            listed.push(msg);
        }
        listed
    }
}

/// The pieces and warnings gathered while the faces are read.
struct Builder<'a> {
    file: &'a str,
    name_face: &'a dyn Fn(&FaceOrigin) -> String,
    pieces: Vec<Piece>,
    warnings: Warnings,
}

impl Builder<'_> {
    fn warn(&mut self, msg: String) {
        self.warnings.push(msg);
    }

    fn skip_degenerate(&mut self, origin: &FaceOrigin) {
        let msg = format!(
            "{}{}: {} is degenerate (zero area) and was skipped",
            self.file,
            at(origin),
            (self.name_face)(origin)
        );
        self.warn(msg);
    }

    /// Adds a face that is planar within the tolerance: flattened onto its
    /// Newell plane (a triangle is kept as it is) and split into convex
    /// pieces; skipped if degenerate.
    fn add_planar(
        &mut self,
        vertices: &[DVec3],
        material: usize,
        origin: &FaceOrigin,
        uv: Option<UvMap>,
    ) -> Result<(), String> {
        let d = diameter(vertices);
        let n = newell_normal(vertices);
        if d == 0.0 || n.length() <= REL_AREA_EPS * d * d {
            self.skip_degenerate(origin);
            return Ok(());
        }
        let normal = n.normalize();
        // Flatten onto the Newell plane, so that `normal · x = offset` holds
        // exactly for the pieces. A triangle lies in its plane already (to
        // rounding): moving its vertices by an ulp would only unshare the
        // edges it shares with its neighbours.
        let flat: Vec<DVec3> = if vertices.len() == 3 {
            vertices.to_vec()
        } else {
            let c = centroid(vertices);
            vertices.iter().map(|p| *p - normal * normal.dot(*p - c)).collect()
        };
        match convex_pieces(&flat) {
            Ok(convex) => self.pieces.extend(convex.into_iter().map(|vertices| Piece {
                vertices,
                normal,
                material,
                origin: origin.clone(),
                uv,
            })),
            Err(PolygonError::Degenerate) => self.skip_degenerate(origin),
            Err(e) => return Err(e.to_string()),
        }
        Ok(())
    }
}

/// Validates, splits and normalises polygons given in scene units (each
/// counter-clockwise about its front) into a [`Scene`]: the mechanism behind
/// every importer and [`Scene::from_polygons`]. `file` names the source in
/// errors and warnings; a [`FaceOrigin::line`] of 0 means "no line".
pub(crate) fn build_scene(
    polygons: &[(Vec<DVec3>, usize, FaceOrigin)],
    materials: Vec<Material>,
    options: &ImportOptions,
    file: &str,
) -> Result<(Scene, Vec<String>), Error> {
    build_scene_named(
        polygons,
        materials,
        options,
        file,
        &|o| format!("face #{}", o.face),
        Textured::default(),
        Warnings::default(),
    )
}

/// [`build_scene`] for a format whose faces are better named otherwise than
/// "face #k" (glTF: by mesh and primitive): `name_face` names a face in
/// errors and warnings, which follow those of reading the file (`warnings`: one list, one
/// limit).
pub(crate) fn build_scene_named(
    polygons: &[(Vec<DVec3>, usize, FaceOrigin)],
    mut materials: Vec<Material>,
    options: &ImportOptions,
    file: &str,
    name_face: &dyn Fn(&FaceOrigin) -> String,
    textured: Textured,
    warnings: Warnings,
) -> Result<(Scene, Vec<String>), Error> {
    check_options(options)?;
    let Textured { textures, uvs } = textured;
    for t in &textures {
        t.validate().map_err(|msg| Error::scene(file, None, msg))?;
    }
    for (i, m) in materials.iter().enumerate() {
        if let Some(t) = m.albedo_texture
            && t as usize >= textures.len()
        {
            return Err(Error::scene(
                file,
                None,
                format!(
                    "material '{}' (#{i}) names texture {t}, but there are {}",
                    m.name,
                    textures.len()
                ),
            ));
        }
    }
    let mut builder = Builder {
        file,
        name_face,
        pieces: Vec::new(),
        warnings,
    };
    for (i, m) in materials.iter_mut().enumerate() {
        check_material(m).map_err(|msg| Error::scene(file, None, format!("material '{}' (#{i}): {msg}", m.name)))?;
        if let Some(msg) = cap_mirror(m) {
            builder.warn(format!("{file}: material '{}': {msg}", m.name));
        }
    }
    if polygons.is_empty() {
        return Err(Error::scene(file, None, "the scene has no faces"));
    }
    if polygons.len() > MAX_FACES {
        return Err(Error::scene(
            file,
            None,
            format!("the scene has {} faces, more than {MAX_FACES}", polygons.len()),
        ));
    }

    for (k, (vertices, material, origin)) in polygons.iter().enumerate() {
        let uv = uvs.get(k).copied().flatten();
        let line = (origin.line > 0).then_some(origin.line);
        let fail = |msg: String| Error::scene(file, line, format!("{}: {msg}", name_face(origin)));
        if *material >= materials.len() {
            return Err(fail(format!(
                "material index {material} out of range ({} materials)",
                materials.len()
            )));
        }
        if vertices.len() < 3 {
            return Err(fail(format!("{} vertices, at least 3 are needed", vertices.len())));
        }
        if let Some(p) = vertices.iter().find(|p| !p.is_finite()) {
            return Err(fail(format!("non-finite vertex {p}")));
        }
        let d = diameter(vertices);
        let n = newell_normal(vertices);
        if !d.is_finite() || !n.is_finite() {
            return Err(fail(
                "coordinates so large that the face's extent overflows".to_string(),
            ));
        }
        if d == 0.0 || n.length() <= REL_AREA_EPS * d * d {
            builder.skip_degenerate(origin);
            continue;
        }
        let deviation = planarity_deviation(vertices);
        // A triangle is planar by construction (its deviation is rounding).
        if vertices.len() == 3 || deviation <= options.planarity_tolerance * d {
            builder.add_planar(vertices, *material, origin, uv).map_err(fail)?;
            continue;
        }
        let bent = format!(
            "not planar: a vertex lies {deviation:.3e} from the face's plane, {:.3e} × the face's \
             diameter {d:.3e} (tolerance {:.1e} × diameter)",
            deviation / d,
            options.planarity_tolerance
        );
        let triangles = match triangulate(vertices) {
            Ok(triangles) => triangles,
            Err(PolygonError::Degenerate) => {
                builder.skip_degenerate(origin);
                continue;
            }
            Err(e) => return Err(fail(format!("{bent}, and in projection onto that plane {e}"))),
        };
        builder.warn(format!(
            "{file}{}: {} is {bent}: split into {} triangles on its own vertices",
            at(origin),
            name_face(origin),
            triangles.len()
        ));
        for t in triangles {
            builder
                .add_planar(&t.map(|i| vertices[i]), *material, origin, uv)
                .map_err(fail)?;
        }
    }
    let Builder {
        pieces, mut warnings, ..
    } = builder;

    if pieces.is_empty() {
        return Err(Error::scene(
            file,
            None,
            "every face is degenerate (zero area): nothing is left of the scene",
        ));
    }
    if !options.object && !pieces.iter().any(|p| materials[p.material].is_emitter()) {
        return Err(Error::scene(
            file,
            None,
            "the scene has no emitter: no face uses a material with Ke > 0, so it would be black",
        ));
    }

    let normalisation = normalisation(pieces.iter().flat_map(|p| p.vertices.iter().copied()))
        .ok_or_else(|| Error::scene(file, None, "the scene's extent is zero or not finite"))?;

    let surfaces = pieces
        .into_iter()
        .map(|p| {
            let vertices: Vec<DVec3> = p.vertices.iter().map(|&x| normalisation.to_vlf(x)).collect();
            let offset = vertices.iter().map(|x| p.normal.dot(*x)).sum::<f64>() / vertices.len() as f64;
            let area = p.normal.dot(newell_normal(&vertices)) / 2.0;
            Surface {
                vertices,
                normal: p.normal,
                offset,
                area,
                material: p.material,
                origin: p.origin,
                uv: p.uv.map(|m| m.scaled(normalisation.center, normalisation.scale)),
            }
        })
        .collect();
    // T-junctions: fans where a neighbour's vertex lies inside an edge, so every edge is shared
    // exactly and the rasteriser leaks no light through them (see `weld`).
    let (surfaces, split) = super::weld::split_t_junctions(surfaces);
    if split > 0 {
        let msg = format!(
            "{file}: {split} face(s) had a neighbour's vertex inside an edge (a T-junction) and were \
             split into triangles there, so no light leaks through the seam"
        );
        warnings.push(msg);
    }

    Ok((
        Scene {
            surfaces,
            materials,
            normalisation,
            textures,
        },
        warnings.into_list(file),
    ))
}

/// `":line"` or nothing, for messages in the `file:line: message` form.
fn at(origin: &FaceOrigin) -> String {
    if origin.line > 0 {
        format!(":{}", origin.line)
    } else {
        String::new()
    }
}

pub(super) fn check_options(options: &ImportOptions) -> Result<(), Error> {
    let t = options.planarity_tolerance;
    if !(t.is_finite() && t >= 0.0) {
        return Err(Error::Parameter(format!(
            "planarity_tolerance must be a finite number ≥ 0, got {t}"
        )));
    }
    Ok(())
}

/// The similarity into the VLF frame: centre of the bounding box, and the
/// farthest vertex from it at exactly (to rounding, never beyond)
/// [`Scene::FRAME_RADIUS`]. `None` for an empty, point-like or overflowing
/// set of points.
fn normalisation(points: impl Iterator<Item = DVec3> + Clone) -> Option<Normalisation> {
    let (lo, hi) = points
        .clone()
        .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p), hi.max(p))
        });
    // Not `(lo + hi) / 2`, which overflows for huge coordinates.
    let center = lo * 0.5 + hi * 0.5;
    if !center.is_finite() {
        return None;
    }
    let radius = |scale: f64| {
        points
            .clone()
            .map(|p| ((p - center) * scale).length())
            .fold(0.0, f64::max)
    };
    let r = radius(1.0);
    let mut scale = Scene::FRAME_RADIUS / r;
    if !(r.is_finite() && r > 0.0 && scale.is_finite()) {
        return None;
    }
    // Rounding may put the farthest vertex an ulp outside the frame.
    for _ in 0..8 {
        if radius(scale) <= Scene::FRAME_RADIUS {
            break;
        }
        scale *= 1.0 - 2.0 * f64::EPSILON;
    }
    Some(Normalisation { center, scale })
}

/// Checks a material's ranges; the message does not name it (callers add
/// where it is defined).
pub(super) fn check_material(m: &Material) -> Result<(), String> {
    let fields = [
        ("diffuse reflectance Kd", m.diffuse),
        ("mirror reflectance Ks (illum 3)", m.specular),
        ("emitted radiance Ke", m.emission),
    ];
    for (label, rgb) in fields {
        if rgb.iter().any(|x| !x.is_finite()) {
            return Err(format!("{label} {} is not finite", fmt_rgb(rgb)));
        }
        if rgb.iter().any(|&x| x < 0.0) {
            return Err(format!("{label} {} is negative", fmt_rgb(rgb)));
        }
    }
    for (label, rgb) in &fields[..2] {
        if rgb.iter().any(|&x| x > 1.0) {
            return Err(format!(
                "{label} {} exceeds 1: a surface cannot reflect more than it receives",
                fmt_rgb(*rgb)
            ));
        }
    }
    for (c, channel) in ["red", "green", "blue"].iter().enumerate() {
        let sum = m.diffuse[c] + m.specular[c];
        // Tolerance for decimal values such as 0.7 + 0.3.
        if sum > 1.0 + 1e-12 {
            return Err(format!(
                "ρd + ρs = Kd + Ks = {sum} exceeds 1 in the {channel} channel \
                 (Kd {}, Ks {} with illum 3): it would create energy",
                fmt_rgb(m.diffuse),
                fmt_rgb(m.specular)
            ));
        }
    }
    Ok(())
}

/// The most faces a scene may have (a double-sided glTF triangle is two): 8 388 608, eight times
/// the largest scans users bring (10⁶ triangles). It bounds what a small file can make the
/// importer hold: a glTF file of a kilobyte may instance one mesh, or read an accessor of 2²⁴
/// implicit zeros, in as many primitives as it likes. Its faces cost about 150 bytes each while
/// they are read, so the limit is about 1.3 GB.
pub const MAX_FACES: usize = 1 << 23;

/// Warnings of one scene listed one by one (a face skipped or split, a material capped…); past
/// them, a count. A scan with a million degenerate slivers has as many warnings, which a log or
/// a job's status cannot show.
pub const MAX_LISTED_WARNINGS: usize = 100;

/// Largest accepted mirror reflectance. Light between two parallel perfect
/// mirrors never dies out, so propagation could not converge; a mirror of
/// `Ks 1` is treated as 0.999 (a warning says so), which keeps the number of
/// bounces to reach a 1e-3 unshot fraction near 7000 in the worst case.
pub const MAX_MIRROR_REFLECTANCE: f64 = 0.999;

/// Caps ρs at [`MAX_MIRROR_REFLECTANCE`]; returns the warning if it did.
fn cap_mirror(m: &mut Material) -> Option<String> {
    if m.specular.iter().all(|&s| s <= MAX_MIRROR_REFLECTANCE) {
        return None;
    }
    let before = fmt_rgb(m.specular);
    for s in &mut m.specular {
        *s = s.min(MAX_MIRROR_REFLECTANCE);
    }
    Some(format!(
        "mirror reflectance Ks {before} capped at {MAX_MIRROR_REFLECTANCE}: a perfect mirror never lets the propagation converge"
    ))
}

pub(super) fn fmt_rgb(c: Rgb) -> String {
    format!("[{}, {}, {}]", c[0], c[1], c[2])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn material(name: &str, diffuse: Rgb, specular: Rgb, emission: Rgb) -> Material {
        Material {
            name: name.to_string(),
            diffuse,
            specular,
            emission,
            albedo_texture: None,
        }
    }

    fn origin(face: usize) -> FaceOrigin {
        FaceOrigin { line: 0, face }
    }

    /// A scene with more degenerate faces than warnings are listed gets the first
    /// [`MAX_LISTED_WARNINGS`] by name and one count of the rest; the faces themselves are all
    /// skipped alike.
    #[test]
    fn warnings_past_the_listed_ones_are_counted() {
        let quad = vec![DVec3::ZERO, DVec3::X, DVec3::new(1.0, 1.0, 0.0), DVec3::Y];
        let line = vec![DVec3::ZERO, DVec3::X, DVec3::X * 2.0];
        let extra = 7;
        let mut polygons = vec![(quad, 0, origin(0))];
        polygons.extend((1..=MAX_LISTED_WARNINGS + extra).map(|f| (line.clone(), 0, origin(f))));
        let light = material("light", [0.0; 3], [0.0; 3], [1.0; 3]);
        let (scene, warnings) = Scene::from_polygons(&polygons, vec![light], &ImportOptions::default()).unwrap();
        assert_eq!(scene.surfaces.len(), 1);
        assert_eq!(
            warnings.len(),
            MAX_LISTED_WARNINGS + 1,
            "{:?}",
            &warnings[MAX_LISTED_WARNINGS - 1..]
        );
        assert!(warnings[MAX_LISTED_WARNINGS - 1].contains(&format!("face #{MAX_LISTED_WARNINGS} is degenerate")));
        assert_eq!(
            warnings[MAX_LISTED_WARNINGS],
            format!("<generated>: {extra} more warnings like those above (not listed)")
        );
    }

    #[test]
    fn programmatic_scenes_share_the_validation() {
        let quad = vec![
            DVec3::new(10.0, 0.0, 0.0),
            DVec3::new(12.0, 0.0, 0.0),
            DVec3::new(12.0, 2.0, 0.0),
            DVec3::new(10.0, 2.0, 0.0),
        ];
        let line = vec![DVec3::ZERO, DVec3::X, DVec3::X * 2.0];
        let polygons = vec![(quad.clone(), 0, origin(0)), (line, 0, origin(1))];
        let light = material("light", [0.0; 3], [0.0; 3], [1.0; 3]);
        let (scene, warnings) =
            Scene::from_polygons(&polygons, vec![light.clone()], &ImportOptions::default()).unwrap();
        assert_eq!(scene.surfaces.len(), 1);
        assert_eq!(warnings.len(), 1);
        assert!(warnings[0].starts_with("<generated>: face #1"), "{}", warnings[0]);
        // A flat square: centre (11, 1, 0), corners at √2.
        assert_eq!(scene.normalisation.center, DVec3::new(11.0, 1.0, 0.0));
        assert!((scene.surfaces[0].area - 2.0 * 0.999 * 0.999).abs() < 1e-12);

        let bad = material("too_bright", [0.7; 3], [0.4; 3], [0.0; 3]);
        let e = Scene::from_polygons(
            &[(quad.clone(), 0, origin(0))],
            vec![light.clone(), bad],
            &ImportOptions::default(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("'too_bright'") && e.contains("red channel"), "{e}");
        assert!(!e.contains(".mtl"), "{e}");

        let e = Scene::from_polygons(
            &[(quad.clone(), 3, origin(0))],
            vec![light.clone()],
            &ImportOptions::default(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("material index 3"), "{e}");

        let nan = vec![DVec3::ZERO, DVec3::X, DVec3::new(f64::NAN, 1.0, 0.0)];
        let e = Scene::from_polygons(&[(nan, 0, origin(0))], vec![light.clone()], &ImportOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("non-finite"), "{e}");

        let huge = vec![
            DVec3::new(-1e308, 0.0, 0.0),
            DVec3::new(1e308, 0.0, 0.0),
            DVec3::new(0.0, 1e308, 0.0),
        ];
        assert!(Scene::from_polygons(&[(huge, 0, origin(0))], vec![light], &ImportOptions::default()).is_err());
    }

    /// A unit emitter quad at z = 0 (face 0) and `face` (face 1).
    fn with_light(face: Vec<DVec3>) -> Vec<(Vec<DVec3>, usize, FaceOrigin)> {
        let light = vec![DVec3::ZERO, DVec3::X, DVec3::new(1.0, 1.0, 0.0), DVec3::Y];
        vec![(light, 0, origin(0)), (face, 1, origin(1))]
    }

    fn materials() -> Vec<Material> {
        vec![
            material("light", [0.0; 3], [0.0; 3], [1.0; 3]),
            material("white", [0.5; 3], [0.0; 3], [0.0; 3]),
        ]
    }

    #[test]
    fn the_planarity_tolerance_chooses_between_flattening_and_triangulating() {
        // Bent by 1e-4 of its diameter.
        let bent = vec![
            DVec3::new(0.0, 0.0, 1.0),
            DVec3::new(1.0, 0.0, 1.0),
            DVec3::new(1.0, 1.0, 1.0 + 4e-4),
            DVec3::new(0.0, 1.0, 1.0),
        ];
        let build = |t: f64| {
            let options = ImportOptions {
                planarity_tolerance: t,
                ..Default::default()
            };
            Scene::from_polygons(&with_light(bent.clone()), materials(), &options).unwrap()
        };
        // Within the default tolerance: flattened and kept whole, silently.
        let (scene, warnings) = build(1e-3);
        assert!(warnings.is_empty(), "{warnings:?}");
        assert_eq!(scene.surfaces.len(), 2);
        let s = &scene.surfaces[1];
        assert_eq!(s.vertices.len(), 4);
        for v in &s.vertices {
            assert!((s.normal.dot(*v) - s.offset).abs() < 1e-15);
        }
        // A vertex moved (onto the plane).
        let moved = bent.iter().map(|&p| scene.normalisation.to_vlf(p));
        assert!(s.vertices.iter().zip(moved).any(|(a, b)| *a != b));

        // Beyond a tighter one: two triangles on the original vertices.
        let (scene, warnings) = build(1e-5);
        assert_eq!(warnings.len(), 1, "{warnings:?}");
        assert!(
            warnings[0].starts_with("<generated>: face #1 is not planar"),
            "{}",
            warnings[0]
        );
        assert!(warnings[0].contains("(tolerance 1.0e-5 × diameter)"), "{}", warnings[0]);
        assert_eq!(scene.surfaces.len(), 3);
        let originals: Vec<DVec3> = bent.iter().map(|&p| scene.normalisation.to_vlf(p)).collect();
        for s in &scene.surfaces[1..] {
            assert_eq!(s.vertices.len(), 3);
            assert_eq!(s.origin, origin(1));
            assert!(s.vertices.iter().all(|v| originals.contains(v)), "{:?}", s.vertices);
            assert!(s.normal.z > 0.99);
        }
        // Exactly planar faces never are split, even at tolerance 0.
        let flat: Vec<DVec3> = bent.iter().map(|p| DVec3::new(p.x, p.y, 1.0)).collect();
        let options = ImportOptions {
            planarity_tolerance: 0.0,
            ..Default::default()
        };
        let (scene, warnings) = Scene::from_polygons(&with_light(flat), materials(), &options).unwrap();
        assert!(warnings.is_empty(), "{warnings:?}");
        assert_eq!(scene.surfaces.len(), 2);
    }

    #[test]
    fn a_triangle_keeps_its_vertices_bit_exact() {
        // Far from the origin and tilted: flattening would round.
        let t = vec![
            DVec3::new(1e3 + 0.1, 2e3 + 0.3, 0.7),
            DVec3::new(1e3 + 1.3, 2e3 + 0.1, 0.9),
            DVec3::new(1e3 + 0.2, 2e3 + 1.7, 1.3),
        ];
        let (scene, _) = Scene::from_polygons(&with_light(t.clone()), materials(), &ImportOptions::default()).unwrap();
        let expected: Vec<DVec3> = t.iter().map(|&p| scene.normalisation.to_vlf(p)).collect();
        assert_eq!(scene.surfaces[1].vertices, expected);
    }

    #[test]
    fn a_bent_self_intersecting_face_is_an_error() {
        let bow = vec![
            DVec3::new(0.0, 0.0, 1.0),
            DVec3::new(3.0, 3.0, 1.5),
            DVec3::new(3.0, 0.0, 1.0),
            DVec3::new(0.0, 1.0, 1.5),
        ];
        let e = Scene::from_polygons(&with_light(bow), materials(), &ImportOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("<generated>: face #1: not planar"), "{e}");
        assert!(e.contains("self-intersecting"), "{e}");
    }
}
