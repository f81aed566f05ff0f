//! Products beside the catalog for looking at a reduction in other tools: DS9 region files
//! ([`regions`]).
pub mod regions;
