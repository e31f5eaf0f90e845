//! The protobuf codec of the SiLA services: prost's, with buffers sized for SiLA's messages.
//! tonic gives every call (each subscription for as long as it lasts) an encode buffer of 8 KiB
//! by default; `IslandControl`'s values are a few hundred bytes to a few KiB, and a buffer grows
//! in steps of its starting size when a message needs more, so starting at 1 KiB costs a long
//! message a few more reallocations and spares every subscriber 7 KiB.

use std::marker::PhantomData;

use tonic::codec::{BufferSettings, Codec};
use tonic_prost::{ProstCodec, ProstDecoder, ProstEncoder};

/// Bytes each call's encode (and decode) buffer starts with, and the step it grows by.
pub const BUFFER: usize = 1024;
/// Bytes of ready messages a stream gathers into one write (tonic's default).
const YIELD_THRESHOLD: usize = 32 * 1024;

/// prost's codec with [`BUFFER`]-sized buffers (`codec_path` of the generated code).
#[derive(Debug, Clone, Copy)]
pub struct SilaCodec<T, U>(PhantomData<(T, U)>);

impl<T, U> Default for SilaCodec<T, U> {
    fn default() -> Self {
        SilaCodec(PhantomData)
    }
}

fn settings() -> BufferSettings {
    BufferSettings::new(BUFFER, YIELD_THRESHOLD)
}

impl<T, U> Codec for SilaCodec<T, U>
where
    T: prost::Message + Send + 'static,
    U: prost::Message + Default + Send + 'static,
{
    type Encode = T;
    type Decode = U;
    type Encoder = ProstEncoder<T>;
    type Decoder = ProstDecoder<U>;

    fn encoder(&mut self) -> Self::Encoder {
        ProstCodec::<T, U>::raw_encoder(settings())
    }

    fn decoder(&mut self) -> Self::Decoder {
        ProstCodec::<T, U>::raw_decoder(settings())
    }
}
