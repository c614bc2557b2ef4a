//! Rounding to integers without a libm call: the baseline x86-64 target has
//! no rounding instruction, and `f64::floor` costs a function call there.

/// ⌊x⌋ for |x| < 2⁶³.
#[inline]
pub(crate) fn floor(x: f64) -> i64 {
    let t = x as i64; // rounds toward zero
    if (t as f64) > x { t - 1 } else { t }
}

/// ⌈x⌉ for |x| < 2⁶³.
#[inline]
pub(crate) fn ceil(x: f64) -> i64 {
    let t = x as i64;
    if (t as f64) < x { t + 1 } else { t }
}

#[cfg(test)]
mod tests {
    #[test]
    fn agrees_with_the_standard_library() {
        for x in [
            -2.5,
            -2.0,
            -1.0000001,
            -0.5,
            -0.0,
            0.0,
            0.3,
            1.0,
            1.5,
            1e12 + 0.5,
        ] {
            assert_eq!(super::floor(x), x.floor() as i64, "{x}");
            assert_eq!(super::ceil(x), x.ceil() as i64, "{x}");
        }
    }
}
