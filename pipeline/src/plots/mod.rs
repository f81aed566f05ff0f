//! PNG figures. (being implemented)
