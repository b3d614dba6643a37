//! Measurements behind `subsurf bench …` whose logic belongs to the library (the commands only
//! parse their flags and print): each returns its figures as data.

pub mod acquisition;
pub mod equivalence;
pub mod fit_scale;
pub mod one_pass;
pub mod tradeoff;
