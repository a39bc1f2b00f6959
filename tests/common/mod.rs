//! Shared helpers of the emc test suite: proptest strategies, hard-case boxes and the location
//! of the shared scenes (tests that need them skip with a message when they are absent).
