//! The OBJ front end of [`crate::scene`]: `.obj` and zstd-compressed `.obj.zst` files, parsed by
//! `tobj` (positions only, triangulated), after a light line check of our own that names the
//! file and line of the first malformed `v`/`vt`/`vn`/`f`/`l` line (`tobj` reports no lines).
#![forbid(unsafe_code)]

use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

use glam::Vec3;

use super::{Mesh, SceneError};

/// zstd window limit of the decoder: 2^27 bytes = 128 MiB (the largest shared scene uses it).
const ZSTD_WINDOW_LOG_MAX: u32 = 27;

/// Load an `.obj` or `.obj.zst` file (by extension). See [`parse_obj_bytes`] for the rules.
pub fn load_obj_file(path: &Path) -> Result<Mesh, SceneError> {
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

/// Read the whole file, decompressing it when its name ends in `.zst` (128 MiB window).
pub fn read_file(path: &Path) -> Result<Vec<u8>, SceneError> {
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

/// Parse OBJ text into a [`Mesh`] named `name`; `path` only names the source in errors.
///
/// Rules: faces with more than three vertices are fan-triangulated by `tobj`; only positions
/// are kept; `mtllib` is ignored; points and lines are ignored (but must be well-formed). A
/// malformed `v`/`vt`/`vn`/`f`/`l` line, an index of 0, an index (absolute or negative
/// relative) that does not name an already defined element, a face with fewer than three
/// vertices, or invalid UTF-8 is a [`SceneError::Malformed`] naming the line. Triangles with
/// a NaN or infinite vertex are dropped and counted in [`Mesh::dropped_nonfinite`]; an error
/// only when none remain. Zero-area triangles are kept.
///
/// The line check runs on a second rayon worker while `tobj` parses, so on two or more idle
/// cores it costs no wall time.
pub fn parse_obj_bytes(bytes: &[u8], path: &Path, name: String) -> Result<Mesh, SceneError> {
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
fn assemble(models: Vec<tobj::Model>, path: &Path, name: String) -> Result<Mesh, SceneError> {
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
    Ok(Mesh {
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
pub fn save_obj(scene: &Mesh, path: &Path) -> Result<(), SceneError> {
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

/// The line check alone (what [`parse_obj_bytes`] runs next to `tobj`): the first malformed
/// line as a [`SceneError::Malformed`] naming `path`.
pub fn check_obj_bytes(bytes: &[u8], path: &Path) -> Result<(), SceneError> {
    check_lines(bytes).map_err(|(line, message)| malformed(path, line, message))
}

/// Counts of the elements defined so far (OBJ indices refer to them).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Counts {
    v: usize,
    vt: usize,
    vn: usize,
}

impl Counts {
    fn get(&self, kind: usize) -> usize {
        [self.v, self.vt, self.vn][kind]
    }
}

/// Bytes per chunk of the parallel line check (a chunk ends after a newline).
const CHECK_CHUNK: usize = 4 << 20;

/// What checking one chunk of lines found.
///
/// Without the element counts of the lines before the chunk (the first, parallel pass) an
/// index can only be checked relative to them: a reference to element `x` (or `-x`) on a line
/// where the chunk itself has defined `c` elements of that kind needs at least `x - c` before
/// the chunk; `need` keeps the largest such value per kind (v, vt, vn).
#[derive(Debug, Default)]
struct ChunkCheck {
    /// Newlines in the chunk (lines it covers, when it ends after a newline).
    lines: usize,
    /// Elements the chunk defines.
    counts: Counts,
    /// Colour form of the chunk's first `v` line and that line (0-based in the chunk).
    first_v: Option<(bool, usize)>,
    /// The first local error: 0-based line in the chunk and message.
    error: Option<(usize, String)>,
    /// Largest number of elements needed before the chunk, per kind.
    need: [usize; 3],
}

/// The line check: `Err((1-based line, message))` for the first malformed line.
fn check_lines(bytes: &[u8]) -> Result<(), (usize, String)> {
    check_lines_chunked(bytes, CHECK_CHUNK)
}

/// The single-chunk (serial) line check.
fn check_lines_serial(bytes: &[u8]) -> Result<(), (usize, String)> {
    let c = check_chunk(bytes, Some((Counts::default(), None)));
    c.error.map_or(Ok(()), |(l, m)| Err((l + 1, m)))
}

/// [`check_lines`] with chunks of about `chunk` bytes, checked in parallel; the same answer as
/// [`check_lines_serial`] for every chunk size.
fn check_lines_chunked(bytes: &[u8], chunk: usize) -> Result<(), (usize, String)> {
    if let Err(e) = std::str::from_utf8(bytes) {
        let at = e.valid_up_to();
        let line = 1 + memchr::memchr_iter(b'\n', &bytes[..at]).count();
        return Err((line, "invalid UTF-8".to_string()));
    }
    // Chunks ending after a newline.
    let mut bounds = vec![0usize];
    while let Some(&last) = bounds.last() {
        if last >= bytes.len() {
            break;
        }
        let target = (last + chunk.max(1)).min(bytes.len());
        let end = match memchr::memchr(b'\n', &bytes[target..]) {
            Some(k) if target < bytes.len() => target + k + 1,
            _ => bytes.len(),
        };
        bounds.push(end);
    }
    if bounds.len() <= 2 {
        return check_lines_serial(bytes);
    }
    use rayon::prelude::*;
    let checks: Vec<ChunkCheck> = bounds
        .par_windows(2)
        .map(|w| check_chunk(&bytes[w[0]..w[1]], None))
        .collect();
    // In order: the first chunk with an error (local, colour, or an index that the elements
    // before it cannot satisfy) holds the first malformed line of the file.
    let mut before = Counts::default();
    let mut line0 = 0usize;
    let mut colour: Option<bool> = None;
    for (k, c) in checks.iter().enumerate() {
        let range_bad = (0..3).any(|kind| c.need[kind] > before.get(kind));
        let colour_bad = matches!((colour, c.first_v), (Some(g), Some((f, _))) if g != f);
        if range_bad || colour_bad || c.error.is_some() {
            // Re-check the chunk knowing what precedes it: it finds the first bad line.
            let exact = check_chunk(&bytes[bounds[k]..bounds[k + 1]], Some((before, colour)));
            let (l, m) = exact
                .error
                .expect("a chunk flagged in the first pass has an error in the second");
            return Err((line0 + l + 1, m));
        }
        if colour.is_none() {
            colour = c.first_v.map(|(f, _)| f);
        }
        before.v += c.counts.v;
        before.vt += c.counts.vt;
        before.vn += c.counts.vn;
        line0 += c.lines;
    }
    Ok(())
}

/// A token for an error message.
fn show(w: &[u8]) -> String {
    String::from_utf8_lossy(w).into_owned()
}

/// ASCII whitespace except the newline.
#[inline(always)]
fn is_blank(b: u8) -> bool {
    matches!(b, b' ' | b'\t' | b'\r' | b'\x0b' | b'\x0c')
}

/// The whitespace-separated words of one line.
struct Words<'a> {
    b: &'a [u8],
    i: usize,
}

impl<'a> Iterator for Words<'a> {
    type Item = &'a [u8];

    #[inline(always)]
    fn next(&mut self) -> Option<&'a [u8]> {
        let (b, n) = (self.b, self.b.len());
        let mut i = self.i;
        while i < n && is_blank(b[i]) {
            i += 1;
        }
        if i == n {
            self.i = i;
            return None;
        }
        let s = i;
        while i < n && !is_blank(b[i]) {
            i += 1;
        }
        self.i = i;
        Some(&b[s..i])
    }
}

/// Check the lines of one chunk.
///
/// With `known = Some((counts before the chunk, colour form of the file's first vertex))`
/// every check is exact and `error` is the first malformed line; with `None` (first pass)
/// index ranges are only gathered into `need` and the colour form is taken from the chunk.
fn check_chunk(b: &[u8], known: Option<(Counts, Option<bool>)>) -> ChunkCheck {
    let mut st = LineState {
        known_before: known.map(|k| k.0),
        colour: known.and_then(|k| k.1),
        counts: Counts::default(),
        need: [0; 3],
        first_v: None,
        line: 0,
    };
    let mut cur = 0usize;
    let mut error = None;
    while cur < b.len() {
        let end = memchr::memchr(b'\n', &b[cur..]).map_or(b.len(), |k| cur + k);
        if let Err(m) = check_line(&b[cur..end], &mut st) {
            error = Some((st.line, m));
            break;
        }
        st.line += 1;
        cur = end + 1;
    }
    ChunkCheck {
        lines: st.line,
        counts: st.counts,
        first_v: st.first_v,
        error,
        need: st.need,
    }
}

/// The running state of [`check_chunk`].
struct LineState {
    known_before: Option<Counts>,
    colour: Option<bool>,
    counts: Counts,
    need: [usize; 3],
    first_v: Option<(bool, usize)>,
    line: usize,
}

/// Check one line (without its newline); counts are advanced for element lines.
#[inline]
fn check_line(line: &[u8], st: &mut LineState) -> Result<(), String> {
    let mut w = Words { b: line, i: 0 };
    // Fast exit for anything that cannot start one of the checked keywords.
    match line.iter().find(|&&c| !is_blank(c)) {
        Some(b'v' | b'f' | b'l' | b'u') => {}
        _ => return Ok(()),
    }
    let Some(key) = w.next() else { return Ok(()) };
    match key {
        b"v" => {
            let mut n = 0;
            let mut fourth: &[u8] = &[];
            for t in w {
                if !is_float(t) {
                    return Err(format!("vertex: `{}` is not a number", show(t)));
                }
                if n == 3 {
                    fourth = t;
                }
                n += 1;
            }
            match n {
                0..=2 => Err(format!("vertex: expected 3 coordinates, found {n}")),
                3 | 6 => {
                    let coloured = n == 6;
                    if st.first_v.is_none() {
                        st.first_v = Some((coloured, st.line));
                    }
                    if *st.colour.get_or_insert(coloured) != coloured {
                        return Err(format!(
                            "vertex: r g b colours must be on every vertex or none (first \
                             vertex {} them)",
                            if coloured { "lacks" } else { "has" }
                        ));
                    }
                    st.counts.v += 1;
                    Ok(())
                }
                4 => {
                    // A lone fourth value is a homogeneous w that divides x, y and z.
                    if parse_f32(fourth) == 0.0 {
                        return Err("vertex: homogeneous w = 0".to_string());
                    }
                    if st.first_v.is_none() {
                        st.first_v = Some((false, st.line));
                    }
                    if *st.colour.get_or_insert(false) {
                        return Err("vertex: r g b colours must be on every vertex or none \
                                    (first vertex has them)"
                            .to_string());
                    }
                    st.counts.v += 1;
                    Ok(())
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
                st.counts.vt += 1;
            } else {
                st.counts.vn += 1;
            }
            Ok(())
        }
        b"f" | b"l" => {
            let what = if key == b"f" { "face" } else { "line" };
            let need = if key == b"f" { 3 } else { 2 };
            let mut n = 0;
            for t in w {
                check_ref(t, st).map_err(|m| format!("{what}: {m}"))?;
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

/// Check one `v`, `v/vt`, `v//vn` or `v/vt/vn` reference.
#[inline]
fn check_ref(t: &[u8], st: &mut LineState) -> Result<(), String> {
    const KINDS: [&str; 3] = ["vertex", "texture coordinate", "normal"];
    let mut parts: [&[u8]; 3] = [&[]; 3];
    let mut k = 0;
    let mut s = 0;
    for (i, &c) in t.iter().enumerate() {
        if c == b'/' {
            if k == 2 {
                return Err(format!("`{}` has more than three `/` parts", show(t)));
            }
            parts[k] = &t[s..i];
            k += 1;
            s = i + 1;
        }
    }
    parts[k] = &t[s..];
    if parts[0].is_empty() {
        return Err(format!("`{}` has no vertex index", show(t)));
    }
    for (kind, p) in parts.iter().enumerate().take(k + 1) {
        if p.is_empty() {
            continue;
        }
        let Some(x) = parse_index(p) else {
            return Err(format!("`{}` is not a valid index", show(t)));
        };
        if x == 0 {
            return Err(format!(
                "{} index 0 in `{}` (indices start at 1)",
                KINDS[kind],
                show(t)
            ));
        }
        let here = st.counts.get(kind);
        let wanted = x.unsigned_abs();
        match st.known_before {
            Some(before) => {
                let defined = before.get(kind) + here;
                if wanted > defined as u64 {
                    return Err(format!(
                        "{} index {x} in `{}` is out of range ({defined} defined so far)",
                        KINDS[kind],
                        show(t)
                    ));
                }
            }
            None => {
                let need = usize::try_from(wanted)
                    .unwrap_or(usize::MAX)
                    .saturating_sub(here);
                st.need[kind] = st.need[kind].max(need);
            }
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

    /// The parallel chunked check gives the serial answer (line and message) for every chunk
    /// size, on valid files and on random damage of them.
    #[test]
    fn chunked_check_equals_serial() {
        let good = "# head\nv 0 0 0 1 0 0\nv 1 0 0 1 0 0\nv 0 1 0 0 1 0\nvt 0 0\nvn 0 0 1\n\
                    f 1/1/1 2/1/1 3/1/1\ng g\nv 0 0 1 1 1 1\nf -1 -2 -3\nf 4 1 2 3\n\
                    l 1 2\nusemtl m\nv 2 2 2 0 0 0\nf 5//1 4//1 -1//1\n";
        let mut rng = crate::scene::builtin::Pcg32::new(3, 3);
        let alphabet = b"vfnt/ -0123456789.e\n#xlg";
        let mut inputs: Vec<Vec<u8>> = vec![good.as_bytes().to_vec()];
        for _ in 0..400 {
            let mut b = good.as_bytes().to_vec();
            for _ in 0..1 + rng.next_u32() % 3 {
                let at = rng.next_u32() as usize % b.len();
                let c = alphabet[rng.next_u32() as usize % alphabet.len()];
                match rng.next_u32() % 3 {
                    0 => b[at] = c,
                    1 => b.insert(at, c),
                    _ => {
                        b.remove(at);
                    }
                }
            }
            inputs.push(b);
        }
        let mut errors = 0;
        for b in &inputs {
            let serial = check_lines_serial(b);
            errors += serial.is_err() as usize;
            for chunk in [1, 2, 3, 5, 8, 13, 40, 1000] {
                assert_eq!(
                    check_lines_chunked(b, chunk),
                    serial,
                    "chunk {chunk}: {:?}",
                    String::from_utf8_lossy(b)
                );
            }
        }
        assert!(check_lines_serial(good.as_bytes()).is_ok());
        // The damage hits both outcomes often.
        assert!(errors > 50 && errors < 390, "{errors}");
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
