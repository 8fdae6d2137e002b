//! 16-bit serial-number arithmetic (RFC 1982, SERIAL_BITS = 16) for stream sequence numbers.

/// Whether `a` precedes `b`.
pub fn lt(a: u16, b: u16) -> bool {
    let d = b.wrapping_sub(a);
    d != 0 && d < 0x8000
}

/// Whether `a` precedes or equals `b`.
pub fn le(a: u16, b: u16) -> bool {
    a == b || lt(a, b)
}

/// The later of two sequence numbers.
pub fn max(a: u16, b: u16) -> u16 {
    if lt(a, b) {
        b
    } else {
        a
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wraps_around() {
        assert!(lt(0xFFFF, 0));
        assert!(lt(0xFFF0, 5));
        assert!(!lt(5, 0xFFF0));
        assert!(!lt(7, 7));
        assert!(le(7, 7));
        assert_eq!(max(0xFFFE, 1), 1);
    }
}
