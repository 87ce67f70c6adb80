#pragma once

#include <cstddef>
#include <string_view>

namespace keyframed {

// How deeply a TOML, JSON or YAML text nests, roughly but never less than its
// parsers see it: the depth of [ and { outside strings and comments, or the count of
// dotted key parts on a line (TOML's a.b.c = 1 or [a.b.c]), whichever is more. The
// parsers recurse once per level (toml++ and OpenCV's FileStorage have no limit), so
// a file nested tens of thousands deep would overflow the stack: callers refuse a
// text deeper than they can need before parsing it.
inline std::size_t textNesting(std::string_view text) {
  std::size_t depth = 0, deepest = 0, dots = 0;
  char quote = 0;
  bool comment = false;
  for (std::size_t i = 0; i < text.size(); ++i) {
    const char c = text[i];
    if (c == '\n') {
      comment = false;
      dots = 0;
      quote = 0;  // (a multi-line string's lines are scanned as text: only ever more)
      continue;
    }
    if (comment) continue;
    if (quote != 0) {
      if (c == '\\' && quote == '"') {
        ++i;
      } else if (c == quote) {
        quote = 0;
      }
      continue;
    }
    switch (c) {
      case '"':
      case '\'': quote = c; break;
      case '#': comment = true; break;
      case '[':
      case '{':
        if (++depth > deepest) deepest = depth;
        break;
      case ']':
      case '}':
        if (depth > 0) --depth;
        break;
      case '.':
        if (++dots > deepest) deepest = dots;
        break;
      default: break;
    }
  }
  return deepest;
}

}  // namespace keyframed
