//! The OBJ front end of [`crate::scene`]: `.obj` and zstd-compressed `.obj.zst` files, parsed by
//! `tobj` (positions only, triangulated), after a light line check of our own that names the
//! file and line of the first malformed `v`/`vt`/`vn`/`f`/`l` line (`tobj` reports no lines).

use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

use glam::Vec3;

use super::{Scene, SceneError};

/// zstd window limit of the decoder: 2^27 bytes = 128 MiB (the largest shared scene uses it).
const ZSTD_WINDOW_LOG_MAX: u32 = 27;

/// Load an `.obj` or `.obj.zst` file (by extension). See [`parse_obj_bytes`] for the rules.
pub fn load_obj_file(path: &Path) -> Result<Scene, SceneError> {
    let bytes = read_file(path)?;
    let name = scene_name(path);
    parse_obj_bytes(&bytes, path, name)
}

/// The stem of a scene file without `.obj` / `.obj.zst`.
fn scene_name(path: &Path) -> String {
    let f = path
        .file_name()
        .map(|f| f.to_string_lossy().into_owned())
        .unwrap_or_default();
    let f = f.strip_suffix(".zst").unwrap_or(&f);
    f.strip_suffix(".obj").unwrap_or(f).to_string()
}

/// Read the whole file, decompressing it when its name ends in `.zst`.
fn read_file(path: &Path) -> Result<Vec<u8>, SceneError> {
    let open = |e| SceneError::Open {
        path: path.to_path_buf(),
        source: e,
    };
    let read = |e| SceneError::Read {
        path: path.to_path_buf(),
        source: e,
    };
    let file = std::fs::File::open(path).map_err(open)?;
    let len = file.metadata().map(|m| m.len() as usize).unwrap_or(0);
    let mut bytes = Vec::new();
    if path.extension().is_some_and(|e| e == "zst") {
        let mut dec =
            zstd::stream::read::Decoder::with_buffer(BufReader::with_capacity(1 << 20, file))
                .map_err(read)?;
        dec.window_log_max(ZSTD_WINDOW_LOG_MAX).map_err(read)?;
        bytes.reserve(len.saturating_mul(5));
        dec.read_to_end(&mut bytes).map_err(read)?;
    } else {
        bytes.reserve(len);
        BufReader::new(file).read_to_end(&mut bytes).map_err(read)?;
    }
    Ok(bytes)
}

/// Parse OBJ text into a [`Scene`] named `name`; `path` only names the source in errors.
///
/// Rules: faces with more than three vertices are fan-triangulated by `tobj`; only positions
/// are kept; `mtllib` is ignored; points and lines are ignored (but must be well-formed). A
/// malformed `v`/`vt`/`vn`/`f`/`l` line, an index of 0, an index (absolute or negative
/// relative) that does not name an already defined element, a face with fewer than three
/// vertices, or invalid UTF-8 is a [`SceneError::Malformed`] naming the line. Triangles with
/// a NaN or infinite vertex are dropped and counted in [`Scene::dropped_nonfinite`]; an error
/// only when none remain. Zero-area triangles are kept.
///
/// The line check runs on a second rayon worker while `tobj` parses, so on two or more idle
/// cores it costs no wall time.
pub fn parse_obj_bytes(bytes: &[u8], path: &Path, name: String) -> Result<Scene, SceneError> {
    let (checked, parsed) = rayon::join(
        || check_lines(bytes).map_err(|(line, message)| malformed(path, line, message)),
        || {
            let opts = tobj::LoadOptions {
                triangulate: true,
                single_index: true,
                ignore_points: true,
                ignore_lines: true,
            };
            tobj::load_obj_buf(&mut &bytes[..], &opts, |_| {
                Ok((Vec::new(), Default::default()))
            })
        },
    );
    checked?;
    let (models, _materials) = parsed.map_err(|e| SceneError::Obj {
        path: path.to_path_buf(),
        source: e,
    })?;
    assemble(models, path, name)
}

fn malformed(path: &Path, line: usize, message: String) -> SceneError {
    SceneError::Malformed {
        path: path.to_path_buf(),
        line,
        message,
    }
}

/// Concatenate `tobj`'s models into one mesh and drop triangles with non-finite vertices.
fn assemble(models: Vec<tobj::Model>, path: &Path, name: String) -> Result<Scene, SceneError> {
    let nv: usize = models.iter().map(|m| m.mesh.positions.len() / 3).sum();
    let nt: usize = models.iter().map(|m| m.mesh.indices.len() / 3).sum();
    if nv > u32::MAX as usize {
        return Err(SceneError::TooLarge {
            path: path.to_path_buf(),
            count: nv,
        });
    }
    let mut vertices = Vec::with_capacity(nv);
    let mut indices = Vec::with_capacity(nt);
    let mut dropped = 0usize;
    for m in &models {
        let base = vertices.len() as u32;
        let first_new = vertices.len();
        vertices.extend(
            m.mesh
                .positions
                .chunks_exact(3)
                .map(|p| Vec3::new(p[0], p[1], p[2])),
        );
        let verts = &vertices[first_new..];
        for t in m.mesh.indices.chunks_exact(3) {
            let tri = [t[0], t[1], t[2]];
            if tri.iter().all(|&i| verts[i as usize].is_finite()) {
                indices.push([base + tri[0], base + tri[1], base + tri[2]]);
            } else {
                dropped += 1;
            }
        }
    }
    let path = PathBuf::from(path);
    if indices.is_empty() {
        return Err(if dropped > 0 {
            SceneError::AllNonFinite { path, dropped }
        } else {
            SceneError::NoTriangles { path }
        });
    }
    Ok(Scene {
        name,
        vertices,
        indices,
        dropped_nonfinite: dropped,
    })
}

/// Write a scene as OBJ (`v` and `f` lines only; zstd-compressed when the name ends in
/// `.zst`, with a 128 MiB window like the largest shared scene). Coordinates are printed in
/// the shortest form that reads back to the same `f32`, so [`load_obj_file`] returns the same
/// triangles (vertices may be renumbered in order of first use).
pub fn save_obj(scene: &Scene, path: &Path) -> Result<(), SceneError> {
    use std::io::Write;
    let io = |e| SceneError::Write {
        path: path.to_path_buf(),
        source: e,
    };
    let file = std::fs::File::create(path).map_err(io)?;
    let write_all = |w: &mut dyn Write| -> std::io::Result<()> {
        writeln!(w, "# {}", scene.name)?;
        for v in &scene.vertices {
            writeln!(w, "v {} {} {}", v.x, v.y, v.z)?;
        }
        for t in &scene.indices {
            writeln!(w, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1)?;
        }
        Ok(())
    };
    if path.extension().is_some_and(|e| e == "zst") {
        let mut enc = zstd::stream::write::Encoder::new(file, 3).map_err(io)?;
        enc.window_log(ZSTD_WINDOW_LOG_MAX).map_err(io)?;
        enc.long_distance_matching(true).map_err(io)?;
        let mut buf = std::io::BufWriter::new(enc);
        write_all(&mut buf).map_err(io)?;
        let enc = buf.into_inner().map_err(|e| io(e.into_error()))?;
        enc.finish().map_err(io)?;
    } else {
        let mut buf = std::io::BufWriter::new(file);
        write_all(&mut buf).map_err(io)?;
        buf.flush().map_err(io)?;
    }
    Ok(())
}

/// Counts of the elements defined so far (OBJ indices refer to them).
#[derive(Default)]
struct Counts {
    /// Whether the first `v` line had r g b colours (`tobj` needs all or none).
    coloured: Option<bool>,
    v: usize,
    vt: usize,
    vn: usize,
}

/// The line check: `Err((1-based line, message))` for the first malformed line.
fn check_lines(bytes: &[u8]) -> Result<(), (usize, String)> {
    if let Err(e) = std::str::from_utf8(bytes) {
        let at = e.valid_up_to();
        let line = 1 + bytes[..at].iter().filter(|&&b| b == b'\n').count();
        return Err((line, "invalid UTF-8".to_string()));
    }
    let mut counts = Counts::default();
    for (k, raw) in bytes.split(|&b| b == b'\n').enumerate() {
        check_line(raw, &mut counts).map_err(|m| (k + 1, m))?;
    }
    Ok(())
}

#[inline]
fn words(line: &[u8]) -> impl Iterator<Item = &[u8]> {
    line.split(|b| b.is_ascii_whitespace())
        .filter(|w| !w.is_empty())
}

fn show(w: &[u8]) -> String {
    String::from_utf8_lossy(w).into_owned()
}

/// Check one line; counts are advanced for vertex lines.
#[inline]
fn check_line(line: &[u8], c: &mut Counts) -> Result<(), String> {
    // Fast exits: blank lines, comments and anything not starting with v/f/l/u.
    match line.first() {
        Some(b'v' | b'f' | b'l' | b'u') => {}
        Some(b) if b.is_ascii_whitespace() => {}
        _ => return Ok(()),
    }
    let mut w = words(line);
    let Some(key) = w.next() else { return Ok(()) };
    match key {
        b"v" => {
            let mut n = 0;
            for t in w {
                if !is_float(t) {
                    return Err(format!("vertex: `{}` is not a number", show(t)));
                }
                n += 1;
            }
            match n {
                0..=2 => Err(format!("vertex: expected 3 coordinates, found {n}")),
                3 | 6 => {
                    let coloured = n == 6;
                    if *c.coloured.get_or_insert(coloured) != coloured {
                        return Err(format!(
                            "vertex: r g b colours must be on every vertex or none (first \
                             vertex {} them)",
                            if coloured { "lacks" } else { "has" }
                        ));
                    }
                    c.v += 1;
                    Ok(())
                }
                4 => {
                    // A lone fourth value is a homogeneous w that divides x, y and z.
                    let wv = words(line).nth(4).map(parse_f32).unwrap_or(1.0);
                    if wv == 0.0 {
                        Err("vertex: homogeneous w = 0".to_string())
                    } else {
                        c.v += 1;
                        Ok(())
                    }
                }
                _ => Err(format!(
                    "vertex: expected 3 coordinates (+ w or r g b), found {n} numbers"
                )),
            }
        }
        b"vt" | b"vn" => {
            let need = if key == b"vt" { 2 } else { 3 };
            let mut n = 0;
            for t in w.by_ref().take(need) {
                if !is_float(t) {
                    return Err(format!("{}: `{}` is not a number", show(key), show(t)));
                }
                n += 1;
            }
            if n < need {
                return Err(format!("{}: expected {need} numbers, found {n}", show(key)));
            }
            if key == b"vt" {
                c.vt += 1;
            } else {
                c.vn += 1;
            }
            Ok(())
        }
        b"f" | b"l" => {
            let what = if key == b"f" { "face" } else { "line" };
            let need = if key == b"f" { 3 } else { 2 };
            let mut n = 0;
            for t in w {
                check_ref(t, c).map_err(|m| format!("{what}: {m}"))?;
                n += 1;
            }
            if n < need {
                Err(format!("{what}: needs at least {need} vertices, found {n}"))
            } else {
                Ok(())
            }
        }
        b"usemtl" => {
            if w.next().is_none() {
                Err("usemtl without a material name".to_string())
            } else {
                Ok(())
            }
        }
        _ => Ok(()),
    }
}

/// Check one `v`, `v/vt`, `v//vn` or `v/vt/vn` reference against the counts so far.
#[inline]
fn check_ref(t: &[u8], c: &Counts) -> Result<(), String> {
    if t.iter().filter(|&&b| b == b'/').count() > 2 {
        return Err(format!("`{}` has more than three `/` parts", show(t)));
    }
    let mut parts = t.split(|&b| b == b'/');
    let kinds = [
        ("vertex", c.v),
        ("texture coordinate", c.vt),
        ("normal", c.vn),
    ];
    for (k, (kind, count)) in kinds.iter().enumerate() {
        let Some(p) = parts.next() else { break };
        if p.is_empty() {
            if k == 0 {
                return Err(format!("`{}` has no vertex index", show(t)));
            }
            continue;
        }
        let Some(x) = parse_index(p) else {
            return Err(format!("`{}` is not a valid index", show(t)));
        };
        if x == 0 {
            return Err(format!(
                "{kind} index 0 in `{}` (indices start at 1)",
                show(t)
            ));
        }
        let ok = if x > 0 {
            x as u64 <= *count as u64
        } else {
            x.unsigned_abs() <= *count as u64
        };
        if !ok {
            return Err(format!(
                "{kind} index {x} in `{}` is out of range ({count} defined so far)",
                show(t)
            ));
        }
    }
    Ok(())
}

/// A signed decimal integer as `isize::from_str` accepts it; `None` on bad syntax or overflow.
#[inline]
fn parse_index(s: &[u8]) -> Option<i64> {
    let (neg, digits) = match s {
        [b'-', rest @ ..] => (true, rest),
        [b'+', rest @ ..] => (false, rest),
        _ => (false, s),
    };
    if digits.is_empty() {
        return None;
    }
    let mut v: i64 = 0;
    for &d in digits {
        if !d.is_ascii_digit() {
            return None;
        }
        v = v.checked_mul(10)?.checked_add((d - b'0') as i64)?;
    }
    Some(if neg { -v } else { v })
}

/// Full parse of a token already known to be a valid float (rare path: w values only).
fn parse_f32(t: &[u8]) -> f32 {
    std::str::from_utf8(t)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(f32::NAN)
}

/// True when `t` is a float as `f32::from_str` accepts it (syntax only, no conversion):
/// `Sign? ('inf' | 'infinity' | 'nan' | Number)`, `Number ::= (Digit+ | Digit+ '.' Digit* |
/// Digit* '.' Digit+) Exp?`, `Exp ::= [eE] Sign? Digit+`, special words case-insensitive.
#[inline]
fn is_float(t: &[u8]) -> bool {
    let t = match t {
        [b'+' | b'-', rest @ ..] => rest,
        _ => t,
    };
    let mut i = 0;
    let n = t.len();
    while i < n && t[i].is_ascii_digit() {
        i += 1;
    }
    let int_digits = i;
    let mut frac_digits = 0;
    if i < n && t[i] == b'.' {
        i += 1;
        let s = i;
        while i < n && t[i].is_ascii_digit() {
            i += 1;
        }
        frac_digits = i - s;
    }
    if int_digits + frac_digits == 0 {
        return t.eq_ignore_ascii_case(b"inf")
            || t.eq_ignore_ascii_case(b"infinity")
            || t.eq_ignore_ascii_case(b"nan");
    }
    if i < n && (t[i] == b'e' || t[i] == b'E') {
        i += 1;
        if i < n && (t[i] == b'+' || t[i] == b'-') {
            i += 1;
        }
        let s = i;
        while i < n && t[i].is_ascii_digit() {
            i += 1;
        }
        if i == s {
            return false;
        }
    }
    i == n
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn float_syntax_matches_std() {
        let cases = [
            "1",
            "-1",
            "+1",
            "1.",
            ".5",
            "1.5e3",
            "1E-3",
            "-.5e+2",
            "inf",
            "-Infinity",
            "NaN",
            ".",
            "",
            "e5",
            "1e",
            "1e+",
            "1.2.3",
            "--1",
            "0x10",
            "1f",
            "infinit",
            "nan1",
            "+",
        ];
        for c in cases {
            assert_eq!(
                is_float(c.as_bytes()),
                c.parse::<f32>().is_ok(),
                "token `{c}`"
            );
        }
    }

    #[test]
    fn index_syntax_matches_std() {
        for c in ["1", "-3", "+7", "", "-", "1a", "99999999999999999999", "0"] {
            assert_eq!(
                parse_index(c.as_bytes()),
                c.parse::<i64>().ok(),
                "token `{c}`"
            );
        }
    }
}
