// Reading textures and writing images with OpenImageIO (PNG, EXR, anything OIIO writes).
#pragma once

#include <string>
#include <vector>

#include "scenes/scene.h"

namespace rs {

// Writes width x height linear rgb floats (row 0 at the top). 8-bit formats (PNG) get sRGB
// encoding and clamping; EXR gets the floats as they are. The file is written to a temporary
// name beside `path` and renamed on success, so a failed write never leaves a partial image.
// Throws rs::Error naming the path (unwritable directory, unknown extension, I/O error).
void WriteImage(const std::string& path, int width, int height, const std::vector<float>& rgb);

// Reads an image as linear rgb floats (sRGB 8-bit input is decoded). Throws rs::Error.
Texture ReadImage(const std::string& path);

}  // namespace rs
