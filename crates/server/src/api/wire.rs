//! Wire conventions every resource shares: ids (16 lowercase hex digits, the store's `u64`,
//! so they sort by creation time) and the page sizes of the listing routes.

/// Formats a store id for the wire.
pub fn format_id(id: u64) -> String {
    format!("{id:016x}")
}

/// Parses a wire id; `None` when it cannot be an id (callers answer 404).
pub fn parse_id(s: &str) -> Option<u64> {
    if s.len() == 16
        && s.bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
    {
        u64::from_str_radix(s, 16).ok()
    } else {
        None
    }
}

/// Default page size of `GET /v1/localizations` and `GET /v1/maps/{id}/trips`.
pub const DEFAULT_PAGE: usize = 20;
/// Largest page size of those listings.
pub const MAX_PAGE: usize = 100;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_round_trip_and_reject_garbage() {
        assert_eq!(parse_id(&format_id(0xdead_beef)), Some(0xdead_beef));
        for bad in [
            "",
            "123",
            "000000000000000G",
            "00000000000000FF",
            "0000000000000000a",
        ] {
            assert_eq!(parse_id(bad), None, "{bad}");
        }
    }
}
