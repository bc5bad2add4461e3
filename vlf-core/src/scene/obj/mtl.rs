//! MTL material libraries, as the OBJ's `mtllib` statements name them:
//! `newmtl`, `Kd`, `Ks`, `Ke` and `illum` are read (see the OBJ module's
//! conventions); everything else is ignored. Ranges are checked later, for
//! the materials actually used.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use super::{argument, logical_lines};
use crate::Error;
use crate::scene::{Material, Rgb};

/// A material as defined in an MTL file, with where, for error messages.
pub(super) struct MtlEntry {
    pub material: Material,
    pub file: String,
    /// Line of its `newmtl`.
    pub line: usize,
}

/// Reads every library named by the `mtllib` statements (relative to the
/// OBJ file's folder), each once. A later definition of a name replaces an
/// earlier one.
pub(super) fn load_libraries(
    mtllibs: &[(usize, String)],
    dir: &Path,
    obj_file: &str,
    confined: bool,
) -> Result<HashMap<String, MtlEntry>, Error> {
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
            // Confined (a server's upload): a plain file name beside the OBJ, nothing else.
            let plain = Path::new(name).components().count() == 1
                && matches!(
                    Path::new(name).components().next(),
                    Some(std::path::Component::Normal(_))
                );
            if confined && !plain {
                return Err(Error::scene(
                    obj_file,
                    Some(*line),
                    format!(
                        "material library '{name}' is not a plain file name beside the scene: an uploaded \
                         scene may only name the files uploaded with it"
                    ),
                ));
            }
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
            albedo_texture: None,
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
