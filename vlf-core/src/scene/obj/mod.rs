//! Wavefront OBJ + MTL import: the text is read here into polygons and
//! materials; validation, splitting and normalisation are
//! [`build`](super::build)'s, shared with the other formats.
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
//! * **Faces are one-sided**, counter-clockwise about the front; any simple
//!   polygon is accepted, planar or not (see [`build`](super::build): bent
//!   faces are triangulated on their own vertices, with a warning).
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
//!   out of range; a face that intersects itself; a material (named, with
//!   its MTL file and `newmtl` line) with a negative or non-finite
//!   `Kd`/`Ks`/`Ke`, a `Kd` or `Ks` above 1, or ρd + ρs > 1 in a channel; a
//!   scene without faces, without any emitting face (`Ke` > 0), or of zero
//!   extent. Degenerate faces are skipped with a warning. A face's
//!   [`FaceOrigin`] is the line of its `f` and its index among the file's
//!   faces.
//!
//! The OBJ and MTL text is parsed here rather than with `tobj`: `tobj` 4.0.5
//! panics on a one-number colour (`Ke 1`, `Kd 0.5`), reads positions as f32,
//! treats `l` polylines as faces and reports no line numbers, all of which
//! the conventions above rule out.

use std::collections::HashMap;
use std::path::Path;

use glam::DVec3;

use self::mtl::load_libraries;
use super::build::{ImportOptions, build_scene, check_material, check_options};
use super::{FaceOrigin, Scene};
use crate::Error;

mod mtl;
#[cfg(test)]
mod tests;

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
    let library = load_libraries(&obj.mtllibs, dir, &file, options.confined)?;
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
pub(super) fn logical_lines(text: &str) -> Vec<(usize, String)> {
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
pub(super) fn argument<'a>(content: &'a str, keyword: &str) -> &'a str {
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
