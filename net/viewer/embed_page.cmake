# Writes a C++ source defining zone::net::viewer_page() with the bytes of INPUT (the viewer page).
# Run by the build (net/CMakeLists.txt) whenever the page changes: cmake -DINPUT=... -DOUTPUT=... -P
file(READ "${INPUT}" hex HEX)
string(LENGTH "${hex}" hex_length)
math(EXPR byte_count "${hex_length} / 2")
string(REGEX REPLACE "([0-9a-f][0-9a-f])" "0x\\1," bytes "${hex}")
string(REGEX REPLACE "(0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,0x..,)" "\\1\n" bytes "${bytes}")
file(WRITE "${OUTPUT}.tmp" "// Generated from net/viewer/index.html by net/viewer/embed_page.cmake; do not edit.\n"
  "#include <string_view>\n#include \"viewer.h\"\n"
  "namespace zone::net {\nnamespace {\nconstexpr unsigned char page[] = {\n${bytes}0};\n}  // namespace\n"
  "std::string_view viewer_page() { return {reinterpret_cast<const char*>(page), ${byte_count}}; }\n}  // namespace zone::net\n")
file(RENAME "${OUTPUT}.tmp" "${OUTPUT}")
