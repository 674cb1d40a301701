//! The user-facing file formats (`interfaces.md` of the design documents):
//! model files, barrier files, prior means, input maps and CSV data, each
//! parsed strictly with errors that name the field.

pub mod barrier_file;
pub mod csv_data;
pub mod input_map_spec;
pub mod model_file;
pub mod params;
pub mod parse;
pub mod prior_spec;
