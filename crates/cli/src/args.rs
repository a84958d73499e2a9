//! Value parsers shared by the subcommands: numbers refused at the command line, with the
//! reason, instead of running on a value that means nothing.

/// Most environments one command runs at once: beyond it the batched buffers alone outgrow a
/// laptop's memory.
pub const MAX_ENVS: usize = 4096;

/// A duration in seconds: finite, above 0 and at most an hour. Pair it with
/// `allow_negative_numbers = true`, so that `--seconds -2` reaches this check instead of being
/// read as a flag.
pub fn seconds(text: &str) -> Result<f64, String> {
    let value: f64 = text.parse().map_err(|_| format!("'{text}' is not a number of seconds"))?;
    if !(value.is_finite() && value > 0.0 && value <= 3600.0) {
        return Err(format!("{value} s: give a duration above 0 and at most 3600 s"));
    }
    Ok(value)
}

/// A count of environments, 1 to [`MAX_ENVS`].
pub fn envs(text: &str) -> Result<usize, String> {
    let value: usize = text.parse().map_err(|_| format!("'{text}' is not a whole number"))?;
    if !(1..=MAX_ENVS).contains(&value) {
        return Err(format!("{value} environments: give 1 to {MAX_ENVS}"));
    }
    Ok(value)
}

/// A share from 0 to 1 (pair it with `allow_negative_numbers = true`, as [`seconds`]).
pub fn share(text: &str) -> Result<f32, String> {
    let value: f32 = text.parse().map_err(|_| format!("'{text}' is not a number"))?;
    if !(0.0..=1.0).contains(&value) {
        return Err(format!("{value}: give a share from 0 to 1"));
    }
    Ok(value)
}

/// A positive count (trials, episodes, iterations).
pub fn count(text: &str) -> Result<usize, String> {
    match text.parse::<usize>() {
        Ok(0) => Err("0: give at least 1".into()),
        Ok(n) => Ok(n),
        Err(_) => Err(format!("'{text}' is not a whole number")),
    }
}
