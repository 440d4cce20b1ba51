// Private to net/: how the HTTP server (metrics.cpp) hands a /viewer request to the viewer.
#pragma once

#include <boost/beast/core/tcp_stream.hpp>
#include <boost/beast/http/message.hpp>
#include <boost/beast/http/string_body.hpp>
#include <string_view>

#include "viewer.h"

namespace zone::net {

/// True for the targets the viewer answers: /viewer, /viewer/..., /viewer?...
[[nodiscard]] bool is_viewer_target(std::string_view target);

/// Takes over the connection of a request for a viewer target: answers it (the page, JSON, an
/// error) or upgrades it to a /viewer/ws session. Runs on the connection's executor.
void viewer_handoff(viewer_server& viewer, boost::beast::tcp_stream stream,
                    boost::beast::http::request<boost::beast::http::string_body> request);

}  // namespace zone::net
