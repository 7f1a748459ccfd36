//! Runtime choice of instruction set: the dispatch macro lives in `handflow_protocol::isa`,
//! shared with the video decoder; this names it where the flow's filters use it.

pub(crate) use handflow_protocol::vectorised_fn;
