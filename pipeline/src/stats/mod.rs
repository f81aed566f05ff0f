//! Sample statistics: projection / ISM Monte Carlo, KS and Kuiper tests. (being implemented)
