//! Reading numbers back as written: serde_json writes a non-finite f64 as `null`, which
//! plain `f64` refuses. These read `null` as NaN, and keep a key that was present present
//! (`Some(NaN)`), so a catalog read and written again is unchanged.
use serde::{Deserialize, Deserializer};

/// NaN: the default of a number a catalog lacks.
pub fn nan() -> f64 {
    f64::NAN
}

/// A number, `null` read as NaN.
pub fn num<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// A present number (`null` read as NaN); an absent key is `None` (`serde(default)`).
pub fn opt<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
    num(d).map(Some)
}

/// A present list of numbers, each `null` read as NaN.
pub fn list<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Vec<f64>>, D::Error> {
    let v = Vec::<Option<f64>>::deserialize(d)?;
    Ok(Some(v.into_iter().map(|x| x.unwrap_or(f64::NAN)).collect()))
}

/// A present pair of numbers, each `null` read as NaN.
pub fn pair<'de, D: Deserializer<'de>>(d: D) -> Result<Option<[f64; 2]>, D::Error> {
    let [a, b] = <[Option<f64>; 2]>::deserialize(d)?;
    Ok(Some([a.unwrap_or(f64::NAN), b.unwrap_or(f64::NAN)]))
}

/// A present N x N matrix of numbers, each `null` read as NaN; another shape is refused.
pub fn square<'de, D: Deserializer<'de>, const N: usize>(d: D) -> Result<Option<[[f64; N]; N]>, D::Error> {
    let rows = Vec::<Vec<Option<f64>>>::deserialize(d)?;
    let mut m = [[f64::NAN; N]; N];
    if rows.len() != N || rows.iter().any(|r| r.len() != N) {
        return Err(serde::de::Error::custom(format_args!("expected a {N} x {N} matrix")));
    }
    for (row, r) in m.iter_mut().zip(rows) {
        for (v, x) in row.iter_mut().zip(r) {
            *v = x.unwrap_or(f64::NAN);
        }
    }
    Ok(Some(m))
}

/// A present value that may be `null` (`Some(None)`), unlike serde's `Option<Option<T>>`,
/// which reads `null` as absent.
pub fn present<'de, D: Deserializer<'de>, T: Deserialize<'de>>(d: D) -> Result<Option<Option<T>>, D::Error> {
    Option::<T>::deserialize(d).map(Some)
}

/// A pair of numbers that is always present, each `null` read as NaN.
pub fn fixed_pair<'de, D: Deserializer<'de>>(d: D) -> Result<[f64; 2], D::Error> {
    let v: [Option<f64>; 2] = Deserialize::deserialize(d)?;
    Ok(v.map(|x| x.unwrap_or(f64::NAN)))
}

/// A list of numbers that is always present, each `null` read as NaN.
pub fn num_list<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f64>, D::Error> {
    let v: Vec<Option<f64>> = Deserialize::deserialize(d)?;
    Ok(v.into_iter().map(|x| x.unwrap_or(f64::NAN)).collect())
}
