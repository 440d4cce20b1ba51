// Public API of the net layer's wire protocol (docs/protocol.md), all of it: message types, the
// framing codec (pure: bytes in, messages or a typed error out; no sockets), position/velocity
// quantization and the visible-set digest that clients use to verify their view. Each part has a
// header of its own, for code that needs only that part:
//   net/messages.h        the value types (`message`), protocol_version, frame_header_bytes
//   net/codec.h           encoder, tick_update_writer, frame_cost, frame_decoder, decode_frame
//   net/quantizer.h       position_quantizer, quantize_velocity
//   net/digest.h          the visible-set digest
//   net/id_map.h          id_map (the client view's entity table)
//   net/client_view.h     client_view
//   net/client_strings.h  check_player_name, escape_for_log
//
// The schema is net/protocol.fbs; flatc generates protocol_generated.h into the build tree at build
// time. Code that wants zero-copy access to a received frame uses the generated accessors
// (namespace zone::net::wire) on frame_view::envelope; everything else can use the plain value
// types (`message`), which the encoder and `to_message` convert from and to.
#pragma once

#include "net/client_strings.h"
#include "net/client_view.h"
#include "net/codec.h"
#include "net/digest.h"
#include "net/id_map.h"
#include "net/messages.h"
#include "net/quantizer.h"
