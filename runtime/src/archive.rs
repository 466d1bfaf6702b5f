//! What a plan's NNEF archive may hold, checked before tract-nnef reads it.
//!
//! tract-nnef's text parser (nom) backtracks: every bracket, parenthesis or sign that nests an
//! expression one level deeper doubles the work on what is inside it, so a graph of a few
//! kilobytes with a hundred open brackets parses for longer than the universe is old (found by
//! fuzzing the plan loader). The plans `prl compile` writes nest at most 6 levels. An archive is
//! read only when it is an uncompressed tar of `graph.nnef`, an optional `graph.quant` and `.dat`
//! tensors (tract would also open nested model archives and gzip, which plans never use), and
//! when the work its text asks of the parser, bounded as [`parse_work`] counts it, stays within
//! [`WORK_PER_BYTE`] times its length.

use std::io::Read;

/// The parser work a text may ask per byte (plus [`WORK_FLOOR`]): the plans `prl` writes ask
/// 1.2-1.6 (PRL-Track fp32 and int8, NanoTrack; most of a graph sits one or two levels deep).
pub const WORK_PER_BYTE: u64 = 16;
/// Work any text may ask, however short: one expression 16 levels deep.
pub const WORK_FLOOR: u64 = 1 << 16;

/// Checks that `bytes`, a plan's graph archive, holds only what a plan holds and that its text
/// parses in time linear in its length. The error is a sentence for the caller to put after the
/// file's name.
pub fn check_graph_archive(bytes: &[u8]) -> Result<(), String> {
    let mut archive = tar::Archive::new(bytes);
    let entries = archive.entries().map_err(|e| format!("not a tar archive: {e}"))?;
    let mut graph = false;
    for entry in entries {
        let mut entry = entry.map_err(|e| format!("not a tar archive: {e}"))?;
        let path = entry.path().map_err(|e| format!("a member's name is unreadable: {e}"))?.into_owned();
        let name = path.to_string_lossy().trim_start_matches("./").to_string();
        if !entry.header().entry_type().is_file() {
            return Err(format!("member `{name}` is not a file (a plan's archive holds only files)"));
        }
        let text = name == "graph.nnef" || name == "graph.quant";
        if !text && !name.ends_with(".dat") {
            return Err(format!("member `{name}` is none of graph.nnef, graph.quant or a .dat tensor"));
        }
        if text {
            graph |= name == "graph.nnef";
            let mut bytes = Vec::new();
            entry.read_to_end(&mut bytes).map_err(|e| format!("member `{name}`: {e}"))?;
            let (work, depth) = parse_work(&bytes);
            let limit = WORK_FLOOR.saturating_add(WORK_PER_BYTE.saturating_mul(bytes.len() as u64));
            if work > limit {
                return Err(format!(
                    "`{name}` nests expressions {depth} levels deep, more than tract-nnef's parser can \
                     read in bounded time (plans written by prl nest at most 6)"
                ));
            }
        }
    }
    if graph {
        Ok(())
    } else {
        Err("the archive has no graph.nnef".into())
    }
}

/// An upper bound on the work tract-nnef's parser does on `text`, in characters read, and the
/// deepest nesting in it. Each character counts `2^depth`, where depth is the number of open
/// brackets and parentheses around it plus, at each of those levels, the signs (`+ - !`) since
/// the level's last `,`, `;` or curly brace (a unary sign takes the whole expression after it as its operand;
/// a binary one is counted too, which only errs on the safe side). Comments and well-formed
/// string literals are skipped as the parser skips them.
pub fn parse_work(text: &[u8]) -> (u64, u32) {
    // Signs at each open level; `depth` is the number of levels beyond the first plus all signs.
    let mut signs: Vec<u32> = vec![0];
    let (mut depth, mut deepest, mut work) = (0u32, 0u32, 0u64);
    let mut i = 0;
    while i < text.len() {
        let c = text[i];
        match c {
            b'#' => {
                i = text[i..].iter().position(|&b| b == b'\n' || b == b'\r').map_or(text.len(), |p| i + p);
                continue;
            }
            b'"' | b'\'' => {
                if let Some(end) = string_end(text, i) {
                    work = work.saturating_add(1u64 << depth.min(63));
                    i = end;
                    continue;
                }
            }
            b'(' | b'[' => {
                signs.push(0);
                depth += 1;
            }
            b')' | b']' => {
                let top = if signs.len() > 1 { 1 + signs.pop().unwrap_or(0) } else { std::mem::take(&mut signs[0]) };
                depth -= top;
            }
            b',' | b';' | b'{' | b'}' => depth -= std::mem::take(signs.last_mut().expect("the first level stays")),
            b'-' if text.get(i + 1) == Some(&b'>') => {}
            b'+' | b'-' | b'!' => {
                *signs.last_mut().expect("the first level stays") += 1;
                depth += 1;
            }
            _ => {}
        }
        deepest = deepest.max(depth);
        if !c.is_ascii_whitespace() {
            work = work.saturating_add(1u64 << depth.min(63));
        }
        i += 1;
    }
    (work, deepest)
}

/// The index just past the string literal opening at `start`, as tract-nnef reads one: `\`
/// escapes any character, and neither quote may appear unescaped inside. `None` when the
/// parser would not read a string there (it then fails at the quote; counting on is safe).
fn string_end(text: &[u8], start: usize) -> Option<usize> {
    let quote = text[start];
    let mut i = start + 1;
    while i < text.len() {
        match text[i] {
            b'\\' => i += 2,
            c if c == quote => return Some(i + 1),
            b'"' | b'\'' => return None,
            _ => i += 1,
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn work(text: &str) -> (u64, u32) {
        parse_work(text.as_bytes())
    }

    #[test]
    fn brackets_parentheses_and_signs_nest() {
        assert_eq!(work("x = a;"), (4, 0));
        assert_eq!(work("x = [[1]];").1, 2);
        assert_eq!(work("x = f(g(1), [2]);").1, 2);
        assert_eq!(work("x = - - - a;").1, 3);
        // `->` is no sign; a fragment or graph header does not nest its body.
        assert_eq!(work("graph g(x) -> (y) { y = -x; }").1, 1);
        // A sign's operand ends at the next comma, semicolon or closing bracket.
        assert_eq!(work("x = [-a, -b, -c];").1, 2);
        assert_eq!(work("x = -[-a]; y = b;"), (work("x = -[-a];").0 + 4, 3));
        assert_eq!(work("x = -(-a); y = [b];").1, 3);
        // Work doubles per level.
        let (w8, _) = work(&format!("x = {}1{};", "[".repeat(8), "]".repeat(8)));
        let (w9, _) = work(&format!("x = {}1{};", "[".repeat(9), "]".repeat(9)));
        assert!(w9 > 2 * w8 - 8, "{w8} {w9}");
        // Unbalanced closers do not underflow; 200 open brackets saturate.
        assert_eq!(work("]]]) x;").1, 0);
        assert_eq!(work(&"[".repeat(200)).0, u64::MAX);
    }

    #[test]
    fn comments_and_strings_are_skipped_as_the_parser_skips_them() {
        assert_eq!(work("x = a; # [[[[[[[[\ny = b;").1, 0);
        assert_eq!(work("x = f(\"[[[[ \\\" ]]]]\");").1, 1);
        // Not a string to the parser (a stray quote inside): its brackets count.
        assert_eq!(work("x = f(\"[[[[ ' ]]]]\");").1, 5);
    }

    fn archive(members: &[(&str, &[u8])]) -> Vec<u8> {
        let mut out = tar::Builder::new(Vec::new());
        for (name, bytes) in members {
            let mut header = tar::Header::new_ustar();
            header.set_size(bytes.len() as u64);
            header.set_mode(0o644);
            header.set_cksum();
            out.append_data(&mut header, name, *bytes).unwrap();
        }
        out.into_inner().unwrap()
    }

    #[test]
    fn only_a_plans_members_with_bounded_nesting_pass() {
        let graph = b"version 1.0;\ngraph g(x) -> (y) {\n  x = external(shape = [1, 3]);\n  y = x;\n}\n";
        check_graph_archive(&archive(&[("graph.nnef", graph), ("w.dat", b"\0\0")])).unwrap();
        check_graph_archive(&archive(&[("./graph.nnef", graph), ("graph.quant", b"\"y\": zero_point_linear_quantize(zero_point = 0, scale = 0.5, bits = 8, signed = false, symmetric = false);\n")]))
            .unwrap();
        let e = check_graph_archive(&archive(&[("graph.nnef", graph), ("inner.nnef.tar", b"")])).unwrap_err();
        assert!(e.contains("`inner.nnef.tar` is none of"), "{e}");
        let e = check_graph_archive(&archive(&[("w.dat", b"")])).unwrap_err();
        assert!(e.contains("no graph.nnef"), "{e}");
        let e = check_graph_archive(b"\x1f\x8b\x08\0 not a tar").unwrap_err();
        assert!(e.starts_with("not a tar archive") || e.contains("no graph.nnef"), "{e}");
        let deep = format!("version 1.0;\ngraph g(x) -> (y) {{ y = {}1{}; }}\n", "[".repeat(40), "]".repeat(40));
        let e = check_graph_archive(&archive(&[("graph.nnef", deep.as_bytes())])).unwrap_err();
        assert!(e.contains("40 levels deep"), "{e}");
    }
}
