//! Exact floats out of JSON text. serde_json, as this crate builds it (no `float_roundtrip`
//! feature), may round a 17-digit number one ulp away from the value that was written;
//! a log must give back the very bits it was given, so the reader takes the number texts
//! from here and parses them with the standard library, which rounds correctly. Owns only
//! the scanning of top-level fields of an already validated JSON object; must not decide
//! what a message means.

/// The raw text of the value of top-level `key` in the JSON object `json`. `None` when the
/// text is not an object of the expected shape or has no such key; callers then keep what
/// serde_json gave them.
pub(super) fn top_level_value<'a>(json: &'a [u8], key: &str) -> Option<&'a [u8]> {
    let mut scan = Scanner { text: json, pos: 0 };
    scan.skip_ws();
    scan.expect(b'{')?;
    loop {
        scan.skip_ws();
        let name = scan.string()?;
        scan.skip_ws();
        scan.expect(b':')?;
        scan.skip_ws();
        let start = scan.pos;
        scan.value()?;
        if name == key.as_bytes() {
            return Some(&json[start..scan.pos]);
        }
        scan.skip_ws();
        match scan.next()? {
            b',' => continue,
            _ => return None,
        }
    }
}

/// The element texts of a JSON array text such as `[1.5, 2e-3]`.
pub(super) fn array_items(array: &[u8]) -> Option<Vec<&[u8]>> {
    let mut scan = Scanner {
        text: array,
        pos: 0,
    };
    scan.expect(b'[')?;
    let mut items = Vec::new();
    scan.skip_ws();
    if scan.peek() == Some(b']') {
        return Some(items);
    }
    loop {
        scan.skip_ws();
        let start = scan.pos;
        scan.value()?;
        items.push(&array[start..scan.pos]);
        scan.skip_ws();
        match scan.next()? {
            b',' => continue,
            b']' => return Some(items),
            _ => return None,
        }
    }
}

/// A JSON number text as the nearest f64; `None` for `null` and anything else.
pub(super) fn number(text: &[u8]) -> Option<f64> {
    // str::parse also takes "inf", "NaN" and a leading '+', which are not JSON numbers.
    let first = *text.first()?;
    let json_number_bytes = text
        .iter()
        .all(|b| b.is_ascii_digit() || matches!(b, b'-' | b'+' | b'.' | b'e' | b'E'));
    if !(first == b'-' || first.is_ascii_digit()) || !json_number_bytes {
        return None;
    }
    std::str::from_utf8(text).ok()?.parse().ok()
}

/// Replaces each of `values` by the exact parse of the matching element of the array at
/// top-level `key`, where that element is a number. Leaves `values` alone when the texts do
/// not line up (they always do for files rigbridge writes).
pub(super) fn refine_array(json: &[u8], key: &str, values: &mut [f64]) {
    let Some(items) = top_level_value(json, key).and_then(array_items) else {
        return;
    };
    if items.len() != values.len() {
        return;
    }
    for (value, item) in values.iter_mut().zip(items) {
        if let Some(exact) = number(item) {
            *value = exact;
        }
    }
}

/// The exact value of the number at top-level `key`, or `fallback`.
pub(super) fn refine_number(json: &[u8], key: &str, fallback: f64) -> f64 {
    top_level_value(json, key)
        .and_then(number)
        .unwrap_or(fallback)
}

struct Scanner<'a> {
    text: &'a [u8],
    pos: usize,
}

impl<'a> Scanner<'a> {
    fn peek(&self) -> Option<u8> {
        self.text.get(self.pos).copied()
    }

    fn next(&mut self) -> Option<u8> {
        let byte = self.peek()?;
        self.pos += 1;
        Some(byte)
    }

    fn expect(&mut self, byte: u8) -> Option<()> {
        (self.next()? == byte).then_some(())
    }

    fn skip_ws(&mut self) {
        while matches!(self.peek(), Some(b' ' | b'\t' | b'\n' | b'\r')) {
            self.pos += 1;
        }
    }

    /// A string's raw content (escapes left as they are), after its opening quote.
    fn string(&mut self) -> Option<&'a [u8]> {
        self.expect(b'"')?;
        let start = self.pos;
        loop {
            match self.next()? {
                b'\\' => {
                    self.next()?;
                }
                b'"' => return self.text.get(start..self.pos - 1),
                _ => {}
            }
        }
    }

    /// Skips one value of any kind. Nesting is counted, not recursed into, so a deep
    /// document cannot overflow the stack.
    fn value(&mut self) -> Option<()> {
        match self.peek()? {
            b'"' => self.string().map(|_| ()),
            b'[' | b'{' => self.nested(),
            _ => {
                let start = self.pos;
                while let Some(byte) = self.peek() {
                    if matches!(byte, b',' | b']' | b'}' | b' ' | b'\t' | b'\n' | b'\r') {
                        break;
                    }
                    self.pos += 1;
                }
                (self.pos > start).then_some(())
            }
        }
    }

    fn nested(&mut self) -> Option<()> {
        let mut depth = 0usize;
        loop {
            match self.peek()? {
                b'"' => {
                    self.string()?;
                    continue;
                }
                b'[' | b'{' => depth += 1,
                b']' | b'}' => {
                    depth = depth.checked_sub(1)?;
                    if depth == 0 {
                        self.pos += 1;
                        return Some(());
                    }
                }
                _ => {}
            }
            self.pos += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_top_level_fields_and_skips_nested_ones() {
        let json = br#"{"a":{"t":[1,"x]"]},"name":["t\"",""],"t":0.30000000000000004,"position":[1e-3, -2.5 ,null]}"#;
        assert_eq!(
            top_level_value(json, "t"),
            Some(&b"0.30000000000000004"[..])
        );
        let items = array_items(top_level_value(json, "position").unwrap()).unwrap();
        assert_eq!(items, vec![&b"1e-3"[..], b"-2.5", b"null"]);
        assert_eq!(number(b"null"), None);
        assert_eq!(number(b"inf"), None);
        assert_eq!(number(b"-2.5"), Some(-2.5));
        assert_eq!(top_level_value(json, "missing"), None);
        assert_eq!(array_items(b"[]"), Some(vec![]));
    }

    #[test]
    fn gives_back_the_bits_serde_json_wrote() {
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        for _ in 0..20_000 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let value = f64::from_bits(state);
            if !value.is_finite() {
                continue;
            }
            let text = serde_json::to_vec(&serde_json::json!({ "t": value })).unwrap();
            assert_eq!(
                refine_number(&text, "t", f64::NAN).to_bits(),
                value.to_bits()
            );
        }
    }

    #[test]
    fn survives_garbage() {
        for text in [
            &b""[..],
            b"{",
            b"{\"a\"",
            b"{\"a\":",
            b"{\"a\":[",
            b"[",
            b"[1,",
            b"\"",
            b"{\"a\":1,}",
        ] {
            let _ = top_level_value(text, "a");
            let _ = array_items(text);
        }
    }
}
