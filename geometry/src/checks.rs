//! Range checks shared by every configuration section's `validate()`: each returns the offending
//! field (its dotted TOML path, e.g. `tracking.pixel_stride`) and why, so that a configuration
//! error names the file and the field.

/// The field (dotted TOML path) that is out of range and why.
pub type FieldError = (&'static str, String);

/// Accepts a finite `v > 0`; NaN, infinities, zero and negative values are refused.
pub fn positive(field: &'static str, v: f64) -> Result<(), FieldError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err((field, format!("must be a positive number, got {v}")))
    }
}

/// Accepts a finite `v >= 0`; NaN, infinities and negative values are refused.
pub fn non_negative(field: &'static str, v: f64) -> Result<(), FieldError> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err((field, format!("must be >= 0, got {v}")))
    }
}

/// Accepts `v` in [0, 1], both ends included; NaN is refused.
pub fn fraction(field: &'static str, v: f64) -> Result<(), FieldError> {
    if (0.0..=1.0).contains(&v) {
        Ok(())
    } else {
        Err((field, format!("must be in [0, 1], got {v}")))
    }
}

/// A Unix nice value that lowers priority: 0 (unchanged) to 19 (lowest).
pub fn nice_value(field: &'static str, v: i32) -> Result<(), FieldError> {
    if (0..=19).contains(&v) {
        Ok(())
    } else {
        Err((field, format!("must be a nice value from 0 to 19, got {v}")))
    }
}

/// Accepts a count of at least 1.
pub fn at_least_one(field: &'static str, v: usize) -> Result<(), FieldError> {
    if v >= 1 {
        Ok(())
    } else {
        Err((field, "must be at least 1".to_string()))
    }
}
