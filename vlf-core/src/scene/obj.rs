//! Wavefront OBJ + MTL import, and the validation shared with programmatic
//! scenes ([`Scene::from_polygons`]).
//!
//! # Conventions
//!
//! * **Geometry.** Only vertex positions (`v`) and faces (`f`) are used;
//!   texture coordinates and normals in face references (`v/vt/vn`) are
//!   checked for syntax and otherwise ignored, and so are lines (`l`) and
//!   points (`p`) (a warning says how many). Indices are 1-based; negative
//!   indices count back from the last vertex defined so far; positive indices
//!   may refer to vertices defined later in the file. A `v` with a fourth
//!   number `w` is divided by it; six numbers are `x y z r g b` (colour
//!   ignored). Lines ending in `\` continue on the next line; `#` starts a
//!   comment.
//! * **Faces are one-sided.** The front is the side from which the vertices
//!   run counter-clockwise (right-hand rule); only the front emits and
//!   reflects. Any simple planar polygon is accepted: convex ones are kept
//!   whole, non-convex ones are split into convex pieces (ear clipping, then
//!   merged back while convex). Every [`Surface`] is convex and
//!   counter-clockwise about its `normal`.
//! * **Materials** (`mtllib`, `usemtl`, `newmtl`): `Kd` is the diffuse
//!   reflectance ρd; `Ke` is the emitted radiance `Le` (W·sr⁻¹·m⁻², front
//!   side, isotropic); `illum 3` marks an ideal mirror of reflectance ρs =
//!   `Ks`, with any other `illum` `Ks` is ignored (ρs = 0). `Kd`, `Ks`, `Ke`
//!   take 1 number (grey) or 3 (RGB); missing ones are 0. Everything else in
//!   the MTL file (`Ka`, `Ns`, `d`, textures…) is ignored. Every face needs a
//!   material: a face before any `usemtl` is an error. Only the materials
//!   used by faces are range-checked and kept in [`Scene::materials`], in
//!   order of first use (a shared library may hold materials that are not
//!   valid here); malformed statements are errors in any material.
//! * **Validation.** Errors name the file and the 1-based line of the
//!   offending statement: a missing or unreadable OBJ file; an `mtllib` that
//!   cannot be read; a `usemtl` of an unknown material; malformed numbers;
//!   a `v` with fewer than 3 numbers or a non-finite coordinate (`nan`,
//!   `1e999`); an `f` with fewer than 3 vertices or an index that is zero or
//!   out of range; a face that is not planar (a vertex farther from the
//!   Newell plane than [`ImportOptions::planarity_tolerance`] × the face's
//!   diameter; the deviation is reported) or that intersects itself; a
//!   material (named, with its MTL file and `newmtl` line) with a negative or
//!   non-finite `Kd`/`Ks`/`Ke`, a `Kd` or `Ks` above 1, or ρd + ρs > 1 in a
//!   channel; a scene without faces, without any emitting face (`Ke` > 0), or
//!   of zero extent. **Degenerate faces** (zero area, e.g. collinear or
//!   repeated vertices) are not errors, since exporters produce them
//!   routinely: they are skipped, with a warning returned alongside the scene
//!   and logged with `tracing::warn!`.
//! * **Normalisation into the VLF frame.** `x_vlf = (x - center) × scale`
//!   where `center` is the centre of the bounding box and `scale` maps the
//!   vertex farthest from it onto [`Scene::FRAME_RADIUS`]; nearly planar
//!   faces are flattened onto their Newell plane first (moving vertices by
//!   at most the planarity tolerance), so that `normal · x = offset` holds
//!   for every vertex. Computed in f64 throughout.
//!
//! The OBJ and MTL text is parsed here rather than with `tobj`: `tobj` 4.0.5
//! panics on a one-number colour (`Ke 1`, `Kd 0.5`), reads positions as f32,
//! treats `l` polylines as faces and reports no line numbers, all of which
//! the conventions above rule out.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use glam::DVec3;

use super::polygon::{
    PolygonError, REL_AREA_EPS, centroid, convex_pieces, diameter, newell_normal, planarity_deviation,
};
use super::{FaceOrigin, Material, Normalisation, Rgb, Scene, Surface};
use crate::Error;

/// Options of the importer.
#[derive(Clone, Debug)]
pub struct ImportOptions {
    /// Largest accepted distance of a face's vertex from the face's Newell
    /// plane, relative to the face's diameter (default `1e-3`). Exporters
    /// write coordinates with few digits, so exact planarity cannot be
    /// asked; a clearly bent face, though, has no single normal and is
    /// refused rather than silently flattened.
    pub planarity_tolerance: f64,
}

impl ImportOptions {
    /// Default of [`ImportOptions::planarity_tolerance`].
    pub const DEFAULT_PLANARITY_TOLERANCE: f64 = 1e-3;
}

impl Default for ImportOptions {
    fn default() -> Self {
        ImportOptions {
            planarity_tolerance: Self::DEFAULT_PLANARITY_TOLERANCE,
        }
    }
}

/// Reads a Wavefront OBJ file (and its MTL libraries) into a validated scene
/// in the VLF frame, following the conventions of the module documentation.
/// Returns the scene and the warnings (skipped degenerate faces, ignored
/// elements), which are also logged.
pub fn load_obj(path: &Path, options: &ImportOptions) -> Result<(Scene, Vec<String>), Error> {
    check_options(options)?;
    let file = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    // Invalid UTF-8 (in a comment, say) must not refuse the file.
    let text = String::from_utf8_lossy(&bytes);
    let obj = scan_obj(&text, &file)?;

    let dir = path.parent().unwrap_or(Path::new(""));
    let library = load_libraries(&obj.mtllibs, dir, &file)?;
    for (line, name) in &obj.usemtl {
        if !library.contains_key(name) {
            let known = if obj.mtllibs.is_empty() {
                "there is no mtllib statement".to_string()
            } else {
                format!("{} material(s) defined in the mtllib files", library.len())
            };
            return Err(Error::scene(
                &file,
                Some(*line),
                format!("usemtl '{name}': unknown material ({known})"),
            ));
        }
    }

    let mut materials = Vec::with_capacity(obj.used.len());
    for name in &obj.used {
        let Some(entry) = library.get(name) else {
            // Every used name went through a usemtl checked above.
            return Err(Error::scene(&file, None, format!("unknown material '{name}'")));
        };
        check_material(&entry.material)
            .map_err(|msg| Error::scene(&entry.file, Some(entry.line), format!("material '{name}': {msg}")))?;
        materials.push(entry.material.clone());
    }

    let polygons: Vec<(Vec<DVec3>, usize, FaceOrigin)> = obj
        .faces
        .iter()
        .enumerate()
        .map(|(k, f)| {
            let vertices = f.vertices.iter().map(|&i| obj.positions[i]).collect();
            let origin = FaceOrigin { line: f.line, face: k };
            (vertices, f.material, origin)
        })
        .collect();

    let (scene, mut warnings) = build_scene(&polygons, materials, options, &file)?;
    if obj.ignored_elements > 0 {
        let msg = format!(
            "{file}: {} line/point element(s) (l, p) ignored: only faces are surfaces",
            obj.ignored_elements
        );
        tracing::warn!("{msg}");
        warnings.insert(0, msg);
    }
    Ok((scene, warnings))
}

/// Validates, splits and normalises polygons given in scene units (each
/// counter-clockwise about its front) into a [`Scene`]: the mechanism behind
/// [`load_obj`] and [`Scene::from_polygons`]. `file` names the source in
/// errors and warnings; a [`FaceOrigin::line`] of 0 means "no line".
pub(crate) fn build_scene(
    polygons: &[(Vec<DVec3>, usize, FaceOrigin)],
    mut materials: Vec<Material>,
    options: &ImportOptions,
    file: &str,
) -> Result<(Scene, Vec<String>), Error> {
    check_options(options)?;
    let mut warnings = Vec::new();
    for (i, m) in materials.iter_mut().enumerate() {
        check_material(m).map_err(|msg| Error::scene(file, None, format!("material '{}' (#{i}): {msg}", m.name)))?;
        if let Some(msg) = cap_mirror(m) {
            let msg = format!("{file}: material '{}': {msg}", m.name);
            tracing::warn!("{msg}");
            warnings.push(msg);
        }
    }
    if polygons.is_empty() {
        return Err(Error::scene(file, None, "the scene has no faces"));
    }

    struct Piece {
        vertices: Vec<DVec3>,
        normal: DVec3,
        material: usize,
        origin: FaceOrigin,
    }
    let mut pieces: Vec<Piece> = Vec::new();
    let mut skip_degenerate = |origin: &FaceOrigin| {
        let msg = format!(
            "{file}{}: face #{} is degenerate (zero area) and was skipped",
            at(origin),
            origin.face
        );
        tracing::warn!("{msg}");
        warnings.push(msg);
    };

    for (vertices, material, origin) in polygons {
        let line = (origin.line > 0).then_some(origin.line);
        let fail = |msg: String| Error::scene(file, line, format!("face #{}: {msg}", origin.face));
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
            skip_degenerate(origin);
            continue;
        }
        let deviation = planarity_deviation(vertices);
        if deviation > options.planarity_tolerance * d {
            return Err(fail(format!(
                "not planar: a vertex lies {deviation:.3e} from the face's plane, {:.3e} × \
                 the face's diameter {d:.3e} (tolerance {:.1e} × diameter)",
                deviation / d,
                options.planarity_tolerance
            )));
        }
        // Flatten onto the Newell plane, so that `normal · x = offset`
        // holds exactly for the pieces.
        let normal = n.normalize();
        let c = centroid(vertices);
        let flat: Vec<DVec3> = vertices.iter().map(|p| *p - normal * normal.dot(*p - c)).collect();
        match convex_pieces(&flat) {
            Ok(convex) => pieces.extend(convex.into_iter().map(|vertices| Piece {
                vertices,
                normal,
                material: *material,
                origin: origin.clone(),
            })),
            Err(PolygonError::Degenerate) => skip_degenerate(origin),
            Err(e) => return Err(fail(e.to_string())),
        }
    }

    if pieces.is_empty() {
        return Err(Error::scene(
            file,
            None,
            "every face is degenerate (zero area): nothing is left of the scene",
        ));
    }
    if !pieces.iter().any(|p| materials[p.material].is_emitter()) {
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
            }
        })
        .collect();

    Ok((
        Scene {
            surfaces,
            materials,
            normalisation,
        },
        warnings,
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

fn check_options(options: &ImportOptions) -> Result<(), Error> {
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
fn check_material(m: &Material) -> Result<(), String> {
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

fn fmt_rgb(c: Rgb) -> String {
    format!("[{}, {}, {}]", c[0], c[1], c[2])
}

// ---------------------------------------------------------------------------
// OBJ text

/// What the scan of an OBJ file keeps.
struct ObjText {
    positions: Vec<DVec3>,
    faces: Vec<ObjFace>,
    /// Every `usemtl` statement: line and material name.
    usemtl: Vec<(usize, String)>,
    /// Every `mtllib` statement: line and argument.
    mtllibs: Vec<(usize, String)>,
    /// Names of the materials used by faces, in order of first use; a face's
    /// `material` indexes this list.
    used: Vec<String>,
    /// Number of `l` and `p` statements.
    ignored_elements: usize,
}

struct ObjFace {
    line: usize,
    /// 0-based indices into `positions`, checked.
    vertices: Vec<usize>,
    material: usize,
}

/// Logical lines of an OBJ/MTL text: 1-based number of the first physical
/// line, content with the comment removed and `\` continuations joined.
fn logical_lines(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut pending: Option<(usize, String)> = None;
    for (i, raw) in text.lines().enumerate() {
        let content = raw.split('#').next().unwrap_or("");
        let (start, mut acc) = pending.take().unwrap_or((i + 1, String::new()));
        let trimmed = content.trim_end();
        if let Some(head) = trimmed.strip_suffix('\\') {
            acc.push_str(head);
            acc.push(' ');
            pending = Some((start, acc));
        } else {
            acc.push_str(content);
            out.push((start, acc));
        }
    }
    if let Some(p) = pending {
        out.push(p);
    }
    out
}

/// The rest of a statement after its keyword, trimmed (names may contain
/// spaces).
fn argument<'a>(content: &'a str, keyword: &str) -> &'a str {
    let s = content.trim_start();
    s.strip_prefix(keyword).unwrap_or("").trim()
}

/// Parses the statements that matter, reporting malformed ones with their
/// line (which `tobj` would not).
fn scan_obj(text: &str, file: &str) -> Result<ObjText, Error> {
    let mut obj = ObjText {
        positions: Vec::new(),
        faces: Vec::new(),
        usemtl: Vec::new(),
        mtllibs: Vec::new(),
        used: Vec::new(),
        ignored_elements: 0,
    };
    let mut used_index: HashMap<String, usize> = HashMap::new();
    let mut current: Option<usize> = None;
    // Positive vertex indices may point forward: checked at the end.
    let mut max_index: Vec<(usize, i64)> = Vec::new();

    for (line, content) in logical_lines(text) {
        let err = |msg: String| Error::scene(file, Some(line), msg);
        let mut words = content.split_whitespace();
        let Some(keyword) = words.next() else {
            continue;
        };
        match keyword {
            "v" => {
                let numbers = words
                    .map(|w| {
                        w.parse::<f64>()
                            .map_err(|_| err(format!("vertex: malformed number '{w}'")))
                    })
                    .collect::<Result<Vec<f64>, Error>>()?;
                if numbers.len() < 3 {
                    return Err(err(format!("vertex: expected 3 coordinates, found {}", numbers.len())));
                }
                let mut p = DVec3::new(numbers[0], numbers[1], numbers[2]);
                if numbers.len() == 4 {
                    let w = numbers[3];
                    if w == 0.0 || !w.is_finite() {
                        return Err(err(format!("vertex: weight w = {w} is invalid")));
                    }
                    p /= w;
                }
                if !p.is_finite() {
                    return Err(err(format!(
                        "vertex: coordinate not finite ({}, {}, {}): NaN or out of range",
                        p.x, p.y, p.z
                    )));
                }
                obj.positions.push(p);
            }
            "f" => {
                let defined = obj.positions.len() as i64;
                let mut vertices = Vec::new();
                let mut largest = 0;
                for w in words {
                    let index = parse_reference(w, defined).map_err(|m| err(format!("face: {m}")))?;
                    largest = largest.max(index);
                    vertices.push(index);
                }
                if vertices.len() < 3 {
                    return Err(err(format!(
                        "face: {} vertex reference(s), at least 3 are needed",
                        vertices.len()
                    )));
                }
                let Some(material) = current else {
                    return Err(err("face without material: no usemtl statement precedes it".to_string()));
                };
                max_index.push((line, largest));
                obj.faces.push(ObjFace {
                    line,
                    // 1-based and ≥ 1 (checked), so `- 1` cannot wrap.
                    vertices: vertices.iter().map(|&i| (i - 1) as usize).collect(),
                    material,
                });
            }
            "usemtl" => {
                let name = argument(&content, keyword);
                if name.is_empty() {
                    return Err(err("usemtl without a material name".to_string()));
                }
                obj.usemtl.push((line, name.to_string()));
                let next = obj.used.len();
                let index = *used_index.entry(name.to_string()).or_insert(next);
                if index == next {
                    obj.used.push(name.to_string());
                }
                current = Some(index);
            }
            "mtllib" => {
                let arg = argument(&content, keyword);
                if arg.is_empty() {
                    return Err(err("mtllib without a file name".to_string()));
                }
                obj.mtllibs.push((line, arg.to_string()));
            }
            "l" | "p" => obj.ignored_elements += 1,
            _ => {}
        }
    }

    let count = obj.positions.len() as i64;
    if let Some(&(line, index)) = max_index.iter().find(|&&(_, i)| i > count) {
        return Err(Error::scene(
            file,
            Some(line),
            format!("face: vertex index {index} out of range: the file has {count} vertices"),
        ));
    }
    Ok(obj)
}

/// One face reference `v`, `v/vt`, `v//vn` or `v/vt/vn`: the position index,
/// 1-based, with negative (relative) indices resolved against the `defined`
/// vertices so far. Positive indices are not bounded here.
fn parse_reference(word: &str, defined: i64) -> Result<i64, String> {
    let parts: Vec<&str> = word.split('/').collect();
    if parts.len() > 3 {
        return Err(format!("malformed vertex reference '{word}'"));
    }
    for (k, part) in parts.iter().enumerate().skip(1) {
        if part.is_empty() {
            continue;
        }
        let what = if k == 1 { "texture" } else { "normal" };
        match part.parse::<i64>() {
            Ok(0) => return Err(format!("{what} index 0 in '{word}' (indices start at 1)")),
            Ok(_) => {}
            Err(_) => return Err(format!("malformed {what} index in '{word}'")),
        }
    }
    let v: i64 = parts[0]
        .parse()
        .map_err(|_| format!("malformed vertex reference '{word}'"))?;
    match v {
        0 => Err(format!("vertex index 0 in '{word}' is invalid (indices start at 1)")),
        v if v < 0 => {
            let resolved = defined + v + 1;
            if resolved < 1 {
                Err(format!(
                    "relative vertex index {v} reaches before the first vertex \
                     ({defined} defined so far)"
                ))
            } else {
                Ok(resolved)
            }
        }
        v => Ok(v),
    }
}

// ---------------------------------------------------------------------------
// MTL text

/// A material as defined in an MTL file, with where, for error messages.
struct MtlEntry {
    material: Material,
    file: String,
    /// Line of its `newmtl`.
    line: usize,
}

/// Reads every library named by the `mtllib` statements (relative to the
/// OBJ file's folder), each once. A later definition of a name replaces an
/// earlier one.
fn load_libraries(mtllibs: &[(usize, String)], dir: &Path, obj_file: &str) -> Result<HashMap<String, MtlEntry>, Error> {
    let mut library = HashMap::new();
    let mut loaded: Vec<PathBuf> = Vec::new();
    for (line, arg) in mtllibs {
        // `mtllib a.mtl b.mtl` names several files, but a file name may also
        // contain spaces: try the whole argument first.
        let names: Vec<&str> = if dir.join(arg).is_file() {
            vec![arg.as_str()]
        } else {
            arg.split_whitespace().collect()
        };
        for name in names {
            let path = dir.join(name);
            if loaded.contains(&path) {
                continue;
            }
            let bytes = std::fs::read(&path).map_err(|e| {
                Error::scene(
                    obj_file,
                    Some(*line),
                    format!("cannot read material library '{name}' ({}): {e}", path.display()),
                )
            })?;
            parse_mtl(
                &String::from_utf8_lossy(&bytes),
                &path.display().to_string(),
                &mut library,
            )?;
            loaded.push(path);
        }
    }
    Ok(library)
}

/// A material being read.
struct PendingMtl {
    name: String,
    line: usize,
    kd: Rgb,
    ks: Rgb,
    ke: Rgb,
    illum: Option<i64>,
}

impl PendingMtl {
    fn finish(self, file: &str, library: &mut HashMap<String, MtlEntry>) {
        let specular = if self.illum == Some(3) { self.ks } else { [0.0; 3] };
        let material = Material {
            name: self.name.clone(),
            diffuse: self.kd,
            specular,
            emission: self.ke,
        };
        library.insert(
            self.name,
            MtlEntry {
                material,
                file: file.to_string(),
                line: self.line,
            },
        );
    }
}

/// Parses an MTL text (`newmtl`, `Kd`, `Ks`, `Ke`, `illum`; the rest is
/// ignored). Ranges are checked later, for the materials actually used.
fn parse_mtl(text: &str, file: &str, library: &mut HashMap<String, MtlEntry>) -> Result<(), Error> {
    let mut current: Option<PendingMtl> = None;
    for (line, content) in logical_lines(text) {
        let err = |msg: String| Error::scene(file, Some(line), msg);
        let mut words = content.split_whitespace();
        let Some(keyword) = words.next() else {
            continue;
        };
        match keyword {
            "newmtl" => {
                if let Some(done) = current.take() {
                    done.finish(file, library);
                }
                let name = argument(&content, keyword);
                if name.is_empty() {
                    return Err(err("newmtl without a material name".to_string()));
                }
                current = Some(PendingMtl {
                    name: name.to_string(),
                    line,
                    kd: [0.0; 3],
                    ks: [0.0; 3],
                    ke: [0.0; 3],
                    illum: None,
                });
            }
            "Kd" | "Ks" | "Ke" | "illum" => {
                let Some(m) = current.as_mut() else {
                    return Err(err(format!("{keyword} before any newmtl")));
                };
                let name = m.name.clone();
                let err = |msg: String| err(format!("material '{name}': {keyword}: {msg}"));
                if keyword == "illum" {
                    let model = match (words.next(), words.next()) {
                        (Some(w), None) => w.parse::<i64>().ok(),
                        _ => None,
                    };
                    m.illum =
                        Some(model.ok_or_else(|| err("expected one integer (the illumination model)".to_string()))?);
                    continue;
                }
                let rgb = parse_rgb(words).map_err(err)?;
                match keyword {
                    "Kd" => m.kd = rgb,
                    "Ks" => m.ks = rgb,
                    _ => m.ke = rgb,
                }
            }
            _ => {}
        }
    }
    if let Some(done) = current {
        done.finish(file, library);
    }
    Ok(())
}

/// A colour statement's numbers: one (grey) or three (RGB).
fn parse_rgb<'a>(words: impl Iterator<Item = &'a str>) -> Result<Rgb, String> {
    let words: Vec<&str> = words.collect();
    if let Some(&w @ ("spectral" | "xyz")) = words.first() {
        return Err(format!("'{w}' colours are not supported: give r g b"));
    }
    let numbers = words
        .iter()
        .map(|w| w.parse::<f64>().map_err(|_| format!("malformed number '{w}'")))
        .collect::<Result<Vec<f64>, String>>()?;
    match numbers[..] {
        [g] => Ok([g; 3]),
        [r, g, b] => Ok([r, g, b]),
        _ => Err(format!("expected 1 or 3 numbers, found {}", numbers.len())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};

    /// Joins lines with `\n`, so that line `k` of a test file is `lines[k-1]`.
    fn text(lines: &[&str]) -> String {
        lines.join("\n") + "\n"
    }

    /// Writes `scene.obj` (and `scene.mtl`) into a fresh folder under the
    /// temp dir, loads it with `options`, removes the folder.
    fn load_with(obj: &str, mtl: Option<&str>, options: &ImportOptions) -> Result<(Scene, Vec<String>), Error> {
        static COUNTER: AtomicUsize = AtomicUsize::new(0);
        let dir = std::env::temp_dir().join(format!(
            "vlf-core-import-test-{}-{}",
            std::process::id(),
            COUNTER.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("scene.obj");
        std::fs::write(&path, obj).unwrap();
        if let Some(mtl) = mtl {
            std::fs::write(dir.join("scene.mtl"), mtl).unwrap();
        }
        let result = load_obj(&path, options);
        std::fs::remove_dir_all(&dir).unwrap();
        result
    }

    fn load(obj: &str, mtl: &str) -> Result<(Scene, Vec<String>), Error> {
        load_with(obj, Some(mtl), &ImportOptions::default())
    }

    /// The error's message, checked to be a `Scene` error.
    fn scene_error(obj: &str, mtl: &str) -> String {
        match load(obj, mtl) {
            Err(e @ Error::Scene { .. }) => e.to_string(),
            Err(e) => panic!("expected a scene error, got {e}"),
            Ok(_) => panic!("expected an error, the scene loaded"),
        }
    }

    fn mtl() -> String {
        text(&[
            "newmtl white",              // 1
            "Kd 0.75 0.75 0.75",         // 2
            "newmtl red",                // 3
            "Kd 0.75 0.25 0.25",         // 4
            "newmtl light",              // 5
            "Kd 0.5",                    // 6
            "Ke 10 10 8",                // 7
            "newmtl mirror",             // 8
            "Kd 0.1 0.1 0.1",            // 9
            "Ks 0.9 0.8 0.9",            // 10
            "illum 3",                   // 11
            "newmtl glossy",             // 12
            "Kd 0.8 0.8 0.8",            // 13
            "Ks 0.5 0.5 0.5",            // 14
            "illum 2",                   // 15
            "newmtl grey_light",         // 16
            "Ke 5",                      // 17
            "newmtl unused_and_invalid", // 18
            "Kd 2 -1 0",                 // 19
        ])
    }

    /// A unit emitter quad (lines 1–7) followed by `extra` from line 8 on.
    fn with_emitter(extra: &[&str]) -> String {
        let mut lines = vec![
            "mtllib scene.mtl",
            "v 0 0 0",
            "v 1 0 0",
            "v 1 1 0",
            "v 0 1 0",
            "usemtl light",
            "f 1 2 3 4",
        ];
        lines.extend_from_slice(extra);
        text(&lines)
    }

    fn cornell() -> String {
        text(&[
            "# Cornell-like box [0,2]³, walls facing inwards", // 1
            "mtllib scene.mtl",                                // 2
            "v 0 0 0",                                         // 3
            "v 2 0 0",
            "v 2 2 0",
            "v 0 2 0",
            "v 0 0 2",
            "v 2 0 2",
            "v 2 2 2",
            "v 0 2 2",               // 10
            "usemtl white",          // 11
            "o floor",               // 12
            "f 1 5 6 2",             // 13 floor, +y
            "f 4 3 7 8",             // 14 ceiling, -y
            "f 1 2 3 4",             // 15 back, +z
            "usemtl red",            // 16
            "f 1 4 8 5",             // 17 left, +x
            "f 2/1/1 6//2 7/3 3",    // 18 right, -x
            "v 0.75 1.99 0.75",      // 19
            "v 1.25 1.99 0.75",      // 20
            "v 1.25 1.99 1.25",      // 21
            "v 0.75 1.99 1.25",      // 22
            "usemtl light",          // 23
            "f -4 -3 -2 -1 # light", // 24, facing down
        ])
    }

    #[test]
    fn cornell_box_loads_and_is_normalised() {
        let (scene, warnings) = load(&cornell(), &mtl()).unwrap();
        assert!(warnings.is_empty(), "{warnings:?}");
        assert_eq!(scene.surfaces.len(), 6);
        // Only the used materials, in order of first use.
        let names: Vec<&str> = scene.materials.iter().map(|m| m.name.as_str()).collect();
        assert_eq!(names, ["white", "red", "light"]);

        let expected = [
            (13, DVec3::Y, "white"),
            (14, DVec3::NEG_Y, "white"),
            (15, DVec3::Z, "white"),
            (17, DVec3::X, "red"),
            (18, DVec3::NEG_X, "red"),
            (24, DVec3::NEG_Y, "light"),
        ];
        for (k, (line, normal, material)) in expected.into_iter().enumerate() {
            let s = &scene.surfaces[k];
            assert_eq!(s.origin, FaceOrigin { line, face: k });
            assert!((s.normal - normal).length() < 1e-12, "{line}: {}", s.normal);
            assert_eq!(scene.materials[s.material].name, material);
            // CCW about the normal, on the plane.
            assert!(newell_normal(&s.vertices).normalize().dot(s.normal) > 1.0 - 1e-12);
            for v in &s.vertices {
                assert!((s.normal.dot(*v) - s.offset).abs() < 1e-12);
            }
        }
        assert_eq!(scene.materials[2].emission, [10.0, 10.0, 8.0]);
        assert_eq!(scene.materials[2].diffuse, [0.5; 3]);

        // Centre of the box, farthest corners at √3.
        let norm = scene.normalisation;
        assert!((norm.center - DVec3::ONE).length() < 1e-15);
        let scale = Scene::FRAME_RADIUS / 3f64.sqrt();
        assert!((norm.scale - scale).abs() < 1e-14);
        let area: f64 = scene.surfaces.iter().map(|s| s.area).sum();
        let expected_area = (5.0 * 4.0 + 0.25) * scale * scale;
        assert!((area - expected_area).abs() < 1e-12, "{area} vs {expected_area}");
        assert!((scene.surfaces[5].area - 0.25 * scale * scale).abs() < 1e-14);

        let radii = scene
            .surfaces
            .iter()
            .flat_map(|s| s.vertices.iter().map(|v| v.length()));
        let max = radii.clone().fold(0.0, f64::max);
        assert!(radii.clone().all(|r| r <= Scene::FRAME_RADIUS));
        assert!(max > Scene::FRAME_RADIUS - 1e-12, "{max}");
        // Back to scene units.
        let corner = norm.to_scene(scene.surfaces[0].vertices[0]);
        assert!((corner - DVec3::ZERO).length() < 1e-12, "{corner}");
    }

    #[test]
    fn crlf_comments_and_continuations_are_read() {
        let obj = "mtllib scene.mtl\r\nv 0 0 0 # origin\r\nv 1 0 0\r\nv 1 1 0\r\n\
                   v 0 1 0\r\nusemtl light\r\nf 1 2 \\\r\n 3 4\r\n";
        let (scene, _) = load(obj, &mtl()).unwrap();
        assert_eq!(scene.surfaces.len(), 1);
        assert_eq!(scene.surfaces[0].vertices.len(), 4);
        assert_eq!(scene.surfaces[0].origin.line, 7);
    }

    #[test]
    fn non_convex_face_splits_into_convex_pieces() {
        // An L-shaped hexagon, area 3, emitting towards +z.
        let obj = text(&[
            "mtllib scene.mtl",
            "v 0 0 0",
            "v 2 0 0",
            "v 2 1 0",
            "v 1 1 0",
            "v 1 2 0",
            "v 0 2 0",
            "usemtl light",
            "f 1 2 3 4 5 6",
        ]);
        let (scene, warnings) = load(&obj, &mtl()).unwrap();
        assert!(warnings.is_empty());
        assert!(scene.surfaces.len() >= 2, "{}", scene.surfaces.len());
        let scale = scene.normalisation.scale;
        let area: f64 = scene.surfaces.iter().map(|s| s.area).sum();
        assert!((area - 3.0 * scale * scale).abs() < 1e-12);
        for s in &scene.surfaces {
            assert_eq!(s.normal, DVec3::Z);
            assert_eq!(s.origin, FaceOrigin { line: 9, face: 0 });
            assert!(super::super::polygon::is_convex(&s.vertices));
            assert!(newell_normal(&s.vertices).normalize().dot(DVec3::Z) > 1.0 - 1e-12);
        }
    }

    #[test]
    fn mirror_needs_illum_3_and_grey_ke() {
        let obj = with_emitter(&[
            "v 0 0 1",
            "v 1 0 1",
            "v 0 1 1",
            "usemtl mirror",
            "f 5 6 7",
            "usemtl glossy",
            "f 5 6 7",
            "usemtl grey_light",
            "f 5 6 7",
        ]);
        let (scene, _) = load(&obj, &mtl()).unwrap();
        let m = |name: &str| scene.materials.iter().find(|m| m.name == name).unwrap().clone();
        let mirror = m("mirror");
        assert_eq!(mirror.specular, [0.9, 0.8, 0.9]);
        assert_eq!(mirror.diffuse, [0.1; 3]);
        assert!(mirror.is_mirror() && !mirror.is_emitter());
        // illum 2: Ks ignored, so 0.8 + 0.5 is no error either.
        let glossy = m("glossy");
        assert_eq!(glossy.specular, [0.0; 3]);
        assert!(!glossy.is_mirror());
        let grey = m("grey_light");
        assert_eq!(grey.emission, [5.0; 3]);
        assert_eq!(grey.diffuse, [0.0; 3]);
    }

    #[test]
    fn degenerate_faces_are_skipped_with_a_warning() {
        let obj = with_emitter(&[
            "v 2 0 0",     // 8: vertex 5, collinear with 1 and 2
            "f 1 2 5",     // 9: collinear
            "f 1 2 2",     // 10: repeated vertex
            "f 3 3 3 3",   // 11: a point
            "f 1 2 5 2 1", // 12: a spike
        ]);
        let (scene, warnings) = load(&obj, &mtl()).unwrap();
        assert_eq!(scene.surfaces.len(), 1);
        assert_eq!(warnings.len(), 4, "{warnings:?}");
        for (w, line) in warnings.iter().zip(9..) {
            assert!(w.contains(&format!("scene.obj:{line}:")), "{w}");
            assert!(w.contains("degenerate"), "{w}");
        }
    }

    #[test]
    fn lines_and_points_are_ignored_with_a_warning() {
        let obj = with_emitter(&["l 1 2 3", "p 4", "l 1 2"]);
        let (scene, warnings) = load(&obj, &mtl()).unwrap();
        assert_eq!(scene.surfaces.len(), 1);
        assert_eq!(warnings.len(), 1);
        assert!(warnings[0].contains("3 line/point element(s)"), "{}", warnings[0]);
    }

    #[test]
    fn missing_files_are_errors() {
        let missing = std::env::temp_dir().join("vlf-core-no-such-dir/none.obj");
        let e = load_obj(&missing, &ImportOptions::default()).unwrap_err();
        assert!(matches!(e, Error::Io { .. }), "{e}");
        assert!(e.to_string().contains("none.obj"), "{e}");

        let obj = text(&["# header", "mtllib nothere.mtl", "usemtl light"]);
        let e = scene_error(&obj, &mtl());
        assert!(e.contains("scene.obj:2:"), "{e}");
        assert!(e.contains("nothere.mtl"), "{e}");
    }

    #[test]
    fn material_reference_errors_name_the_line() {
        let e = scene_error(&with_emitter(&["usemtl nosuch", "f 1 2 3"]), &mtl());
        assert!(e.contains("scene.obj:8:") && e.contains("nosuch"), "{e}");

        let obj = text(&["mtllib scene.mtl", "v 0 0 0", "v 1 0 0", "v 0 1 0", "f 1 2 3"]);
        let e = scene_error(&obj, &mtl());
        assert!(e.contains("scene.obj:5:") && e.contains("usemtl"), "{e}");

        // No mtllib at all.
        let obj = text(&["v 0 0 0", "v 1 0 0", "v 0 1 0", "usemtl light", "f 1 2 3"]);
        let e = scene_error(&obj, &mtl());
        assert!(e.contains("scene.obj:4:") && e.contains("no mtllib"), "{e}");
    }

    #[test]
    fn malformed_vertices_name_the_line() {
        for (bad, what) in [
            ("v 1 x 0", "malformed number 'x'"),
            ("v 1 2", "expected 3 coordinates"),
            ("v nan 0 0", "not finite"),
            ("v 1e999 0 0", "not finite"),
            ("v 0 -inf 0", "not finite"),
            ("v 1 1 1 0", "weight"),
        ] {
            let e = scene_error(&with_emitter(&[bad]), &mtl());
            assert!(e.contains("scene.obj:8:") && e.contains(what), "{bad}: {e}");
        }
    }

    #[test]
    fn malformed_faces_name_the_line() {
        for (bad, what) in [
            ("f 1 2 9", "out of range"),
            ("f 0 1 2", "index 0"),
            ("f -9 1 2", "before the first vertex"),
            ("f 1 2", "at least 3"),
            ("f 1 2 3.5", "malformed vertex reference"),
            ("f 1/a 2 3", "malformed texture index"),
            ("f 1//0 2 3", "normal index 0"),
            ("f 1/2/3/4 2 3", "malformed vertex reference"),
        ] {
            let e = scene_error(&with_emitter(&["v 5 5 5", bad, "v 6 6 6"]), &mtl());
            assert!(e.contains("scene.obj:9:") && e.contains(what), "{bad}: {e}");
        }
        // Forward references are allowed, relative ones count back.
        let obj = with_emitter(&["usemtl white", "f 5 6 -1", "v 0 0 1", "v 1 0 1", "v 0 1 1"]);
        let (scene, _) = load(&obj, &mtl()).unwrap();
        assert_eq!(scene.surfaces.len(), 2);
    }

    #[test]
    fn non_planar_and_self_intersecting_faces_are_errors() {
        let bent = with_emitter(&[
            "v 0 0 1",
            "v 1 0 1",
            "v 1 1 1.1",
            "v 0 1 1",
            "usemtl white",
            "f 5 6 7 8", // 13
        ]);
        let e = scene_error(&bent, &mtl());
        assert!(e.contains("scene.obj:13:") && e.contains("not planar"), "{e}");
        // The measured deviation from the Newell plane (≈ 0.025).
        assert!(e.contains("lies 2.494e-2 from"), "{e}");
        // A looser tolerance accepts it, flattened onto its plane.
        let loose = ImportOptions {
            planarity_tolerance: 0.05,
        };
        let (scene, _) = load_with(&bent, Some(&mtl()), &loose).unwrap();
        let s = &scene.surfaces[1];
        for v in &s.vertices {
            assert!((s.normal.dot(*v) - s.offset).abs() < 1e-12);
        }

        let bow = with_emitter(&[
            "v 0 0 1",
            "v 3 3 1",
            "v 3 0 1",
            "v 0 1 1",
            "usemtl white",
            "f 5 6 7 8", // 13
        ]);
        let e = scene_error(&bow, &mtl());
        assert!(e.contains("scene.obj:13:") && e.contains("self-intersecting"), "{e}");
    }

    #[test]
    fn material_errors_name_the_material_and_mtl_file() {
        for (bad, what) in [
            ("Kd -0.1 0.5 0.5", "negative"),
            ("Kd 1.5", "exceeds 1"),
            ("Ke nan 1 1", "not finite"),
            ("Ke 1 -1 1", "negative"),
            ("Ke 1e999", "not finite"),
        ] {
            let lib = text(&["newmtl light", "Ke 1", "newmtl bad", bad]);
            let e = scene_error(&with_emitter(&["usemtl bad", "f 1 2 3"]), &lib);
            assert!(
                e.contains("scene.mtl:3:") && e.contains("'bad'") && e.contains(what),
                "{bad}: {e}"
            );
        }
        // ρd + ρs > 1 with illum 3 (green channel).
        let lib = text(&[
            "newmtl light",
            "Ke 1",
            "newmtl shiny",
            "Kd 0.5 0.6 0.5",
            "Ks 0.5 0.5 0.5",
            "illum 3",
        ]);
        let e = scene_error(&with_emitter(&["usemtl shiny", "f 1 2 3"]), &lib);
        assert!(e.contains("scene.mtl:3:") && e.contains("'shiny'"), "{e}");
        assert!(e.contains("exceeds 1 in the green channel"), "{e}");
        // Exactly 1 is fine despite decimal rounding.
        let lib = lib
            .replace("Kd 0.5 0.6 0.5", "Kd 0.7 0.7 0.7")
            .replace("Ks 0.5 0.5 0.5", "Ks 0.3");
        assert!(load(&with_emitter(&["usemtl shiny", "f 1 2 3"]), &lib).is_ok());

        for (bad, line, what) in [
            ("Kd 0.5 x 0.5", 3, "malformed number 'x'"),
            ("Kd 0.1 0.2", 3, "expected 1 or 3 numbers"),
            ("Kd spectral file.rfl", 3, "not supported"),
            ("illum three", 3, "illum"),
        ] {
            let lib = text(&["newmtl light", "Ke 1", bad]);
            let e = scene_error(&with_emitter(&[]), &lib);
            assert!(
                e.contains(&format!("scene.mtl:{line}:")) && e.contains(what),
                "{bad}: {e}"
            );
        }
        let e = scene_error(&with_emitter(&[]), &text(&["Kd 1", "newmtl light", "Ke 1"]));
        assert!(e.contains("scene.mtl:1:") && e.contains("before any newmtl"), "{e}");
    }

    #[test]
    fn scenes_without_faces_or_emitters_are_errors() {
        let obj = text(&["mtllib scene.mtl", "v 0 0 0", "v 1 0 0", "v 0 1 0"]);
        let e = scene_error(&obj, &mtl());
        assert!(e.contains("no faces"), "{e}");

        let obj = with_emitter(&[]).replace("usemtl light", "usemtl white");
        let e = scene_error(&obj, &mtl());
        assert!(e.contains("no emitter"), "{e}");

        // The only emitter is degenerate: nothing emits.
        let obj = text(&[
            "mtllib scene.mtl",
            "v 0 0 0",
            "v 1 0 0",
            "v 2 0 0",
            "v 0 1 0",
            "usemtl light",
            "f 1 2 3",
            "usemtl white",
            "f 1 2 4",
        ]);
        let e = scene_error(&obj, &mtl());
        assert!(e.contains("no emitter"), "{e}");
    }

    #[test]
    fn invalid_options_are_parameter_errors() {
        for t in [-1.0, f64::NAN, f64::INFINITY] {
            let options = ImportOptions { planarity_tolerance: t };
            let e = load_with(&with_emitter(&[]), Some(&mtl()), &options).unwrap_err();
            assert!(matches!(e, Error::Parameter(_)), "{e}");
        }
        assert_eq!(ImportOptions::default().planarity_tolerance, 1e-3);
    }

    fn material(name: &str, diffuse: Rgb, specular: Rgb, emission: Rgb) -> Material {
        Material {
            name: name.to_string(),
            diffuse,
            specular,
            emission,
        }
    }

    #[test]
    fn programmatic_scenes_share_the_validation() {
        let origin = |face| FaceOrigin { line: 0, face };
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
}
