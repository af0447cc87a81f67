// PPE-side layout of the SPE-facing main-memory arrays (see cell_image.h).
#include "sim/cell_image.h"

#include <algorithm>
#include <bit>
#include <chrono>
#include <cstring>
#include <limits>
#include <string>

#include "kernels/accel_impl.h"

namespace rs::sim {

CellImage::CellImage(const Scene& scene, const Accel& accel) : scene_(&scene), accel_(&accel) {
  const auto start = std::chrono::steady_clock::now();
  const Accel::Impl& m = AccelImpl(accel);
  const TriangleSoA& tris = m.triangles;
  const Grid& g = m.grid;
  if (tris.size != scene.triangles.size()) {
    throw Error("cell image: the accel holds " + std::to_string(tris.size) +
                " triangles but the scene " + std::to_string(scene.triangles.size()));
  }
  for (int a = 0; a < 3; ++a) {
    grid_.lo[a] = g.lo[a];
    grid_.hi[a] = g.hi[a];
    grid_.cell_size[a] = g.cell_size[a];
    grid_.inv_cell_size[a] = g.inv_cell_size[a];
    grid_.res[a] = g.res[a];
    grid_.shift[a] = m.shift[a];
  }
  grid_.empty = g.empty() ? 1u : 0u;
  grid_.num_cells = g.num_cells;

  // Leaves: the top-level cells, then (two-level) the occupied sub-cells; their triangle lists
  // are the CSR lists the reference traversal tests (two.leaves, or the flat grid's).
  const TwoLevelGrid& two = m.two_level;
  const bool two_level = !g.empty() && !two.empty();
  grid_.two_level = two_level ? 1u : 0u;
  const Grid& lists = two_level ? two.leaves : g;
  const size_t cells = g.num_cells;
  const size_t leaves = two_level ? lists.num_cells : cells;
  std::vector<CellRecord> leaf(leaves);
  size_t bundles = 0;
  for (size_t c = 0; c < leaves; ++c) {
    const uint32_t count = lists.cell_begin[c + 1] - lists.cell_begin[c];
    if (bundles > std::numeric_limits<uint32_t>::max()) {
      throw Error("cell image: more than 2^32 triangle bundles");
    }
    leaf[c] = CellRecord{static_cast<uint32_t>(bundles), count};
    bundles += (count + 3) / 4;
  }
  num_bundles_ = bundles;
  bundles_.Resize(std::max<size_t>(bundles, 1) * sizeof(TriangleBundle));
  bundles_ea_ = Place(bundles_, "triangle bundles");
  TriangleBundle* out = bundles_.As<TriangleBundle>();
  const float nan = std::numeric_limits<float>::quiet_NaN();
  for (size_t c = 0; c < leaves; ++c) {
    const uint32_t begin = lists.cell_begin[c], end = lists.cell_begin[c + 1];
    for (uint32_t k = begin; k < end; k += 4) {
      TriangleBundle& p = out[leaf[c].first_bundle + (k - begin) / 4];
      for (int lane = 0; lane < 4; ++lane) {
        const bool live = k + uint32_t(lane) < end;
        const uint32_t id = live ? lists.tri_ids[k + uint32_t(lane)] : UINT32_MAX;
        p.id[lane] = id;
        for (int v = 0; v < 3; ++v) {
          for (int a = 0; a < 3; ++a) p.p[v][a][lane] = live ? tris.p[v][a][id] : nan;
        }
      }
    }
  }
  cell_records_.Resize(std::max<size_t>(cells, 1) * sizeof(CellRecord));
  cell_records_ea_ = Place(cell_records_, "cell records");
  CellRecord* records = cell_records_.As<CellRecord>();
  for (size_t c = 0; c < cells; ++c) records[c] = leaf[c];
  if (two_level) {
    num_subgrids_ = two.num_records;
    subgrids_.Resize(num_subgrids_ * sizeof(SubGridRecord));
    std::memcpy(subgrids_.data(), two.records.get(), num_subgrids_ * sizeof(SubGridRecord));
    for (size_t c = 0; c < cells; ++c) {
      if (!two.Refined(c)) continue;
      // TwoLevelGrid::Record's index, computed without binding a reference (the records are
      // alignas(128) but allocated 64-B aligned).
      const uint64_t word = two.refined[c >> 6];
      const uint64_t below = (c & 63) == 0 ? 0 : word & (~uint64_t{0} >> (64 - (c & 63)));
      const size_t index = two.refined_rank[c >> 6] + size_t(std::popcount(below));
      records[c] = CellRecord{static_cast<uint32_t>(index), kRefinedCell};
    }
    leaf_records_.Resize(std::max<size_t>(leaves - cells, 1) * sizeof(CellRecord));
    std::copy(leaf.begin() + static_cast<ptrdiff_t>(cells), leaf.end(),
              leaf_records_.As<CellRecord>());
  } else {
    subgrids_.Resize(128);
    leaf_records_.Resize(128);
  }
  subgrids_ea_ = Place(subgrids_, "sub-grid records");
  leaf_records_ea_ = Place(leaf_records_, "leaf records");

  // Shading records.
  const size_t n = scene.triangles.size();
  shading_.Resize(std::max<size_t>(n, 1) * sizeof(ShadingRecord));
  shading_ea_ = Place(shading_, "shading records");
  ShadingRecord* sr = shading_.As<ShadingRecord>();
  const bool normals = !scene.normals.empty();
  const bool uvs = !scene.uvs.empty();
  for (size_t i = 0; i < n; ++i) {
    const glm::uvec3 t = scene.triangles[i];
    const uint32_t idx[3] = {t.x, t.y, t.z};
    for (int v = 0; v < 3; ++v) {
      for (int a = 0; a < 3; ++a) {
        sr[i].p[v][a] = scene.positions[idx[v]][a];
        sr[i].n[v][a] = normals ? scene.normals[idx[v]][a] : 0.0f;
      }
      sr[i].uv[v][0] = uvs ? scene.uvs[idx[v]].x : 0.0f;
      sr[i].uv[v][1] = uvs ? scene.uvs[idx[v]].y : 0.0f;
    }
    sr[i].material = scene.material_ids[i];
  }

  // Texels: copied into 128-B aligned, line-padded buffers so software-cache lines stay inside
  // registered memory.
  texels_.resize(scene.textures.size());
  std::vector<Ea> texel_ea(scene.textures.size());
  for (size_t t = 0; t < scene.textures.size(); ++t) {
    const Texture& tex = scene.textures[t];
    texels_[t].Resize(std::max<size_t>(tex.rgb.size(), 1) * sizeof(float));
    if (!tex.rgb.empty()) std::memcpy(texels_[t].data(), tex.rgb.data(), tex.rgb.size() * 4);
    texel_ea[t] = Place(texels_[t], "texture " + std::to_string(t));
  }

  materials_.Resize(std::max<size_t>(scene.materials.size(), 1) * sizeof(MaterialRecord));
  materials_ea_ = Place(materials_, "material records");
  MaterialRecord* mr = materials_.As<MaterialRecord>();
  for (size_t i = 0; i < scene.materials.size(); ++i) {
    const Material& mat = scene.materials[i];
    MaterialRecord& r = mr[i];
    for (int a = 0; a < 3; ++a) {
      r.diffuse[a] = mat.diffuse[a];
      r.specular[a] = mat.specular[a];
    }
    r.shininess = mat.shininess;
    r.reflectivity = mat.reflectivity;
    r.transmission = mat.transmission;
    r.ior = mat.ior;
    r.texture = mat.texture;
    r.tex_width = 0;
    r.tex_height = 0;
    r.texels = 0;
    if (mat.texture >= 0 && static_cast<size_t>(mat.texture) < scene.textures.size()) {
      const Texture& tex = scene.textures[static_cast<size_t>(mat.texture)];
      // SampleTexture's white fallback: no size or too few texels.
      const bool usable = tex.width > 0 && tex.height > 0 &&
                          tex.rgb.size() >= static_cast<size_t>(tex.width) * tex.height * 3;
      if (usable) {
        r.tex_width = tex.width;
        r.tex_height = tex.height;
        r.texels = texel_ea[static_cast<size_t>(mat.texture)];
      }
    }
  }

  lights_.Resize(std::max<size_t>(scene.lights.size(), 1) * sizeof(LightRecord));
  lights_ea_ = Place(lights_, "lights");
  LightRecord* lr = lights_.As<LightRecord>();
  for (size_t i = 0; i < scene.lights.size(); ++i) {
    for (int a = 0; a < 3; ++a) {
      lr[i].position[a] = scene.lights[i].position[a];
      lr[i].color[a] = scene.lights[i].color[a];
    }
    lr[i].falloff = scene.lights[i].falloff;
  }

  // Occupancy bits, padded to whole lines.
  const size_t words = (cells + 63) / 64;
  occupancy_.Resize(std::max<size_t>(words, 1) * 8);
  if (words > 0) std::memcpy(occupancy_.data(), g.occupancy.get(), words * 8);
  occupancy_ea_ = Place(occupancy_, "occupancy bits");

  build_seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

Ea CellImage::Place(const AlignedBuffer& buffer, std::string name) {
  const Ea ea = next_ea_;
  const Ea align = MainMemory::kRegionAlign;
  next_ea_ = (ea + std::max<size_t>(buffer.size(), 1) + align - 1) / align * align;
  layout_.push_back(Placed{&buffer, std::move(name), ea});
  return ea;
}

void CellImage::Register(MainMemory& memory) const {
  for (const Placed& p : layout_) {
    memory.RegisterAt(p.ea, p.buffer->data(), p.buffer->size(), p.name);
  }
}

size_t CellImage::Bytes() const {
  size_t b = cell_records_.size() + subgrids_.size() + leaf_records_.size() + bundles_.size() +
             shading_.size() + materials_.size() + lights_.size() + occupancy_.size();
  for (const AlignedBuffer& t : texels_) b += t.size();
  return b;
}

void CellImage::FillConstants(FrameConstants* fc) const {
  const Scene& s = *scene_;
  fc->grid = grid_;
  fc->features = s.features;
  for (int a = 0; a < 3; ++a) fc->background[a] = s.background[a];
  fc->ambient = s.ambient;
  fc->has_normals = s.normals.empty() ? 0u : 1u;
  fc->has_uvs = s.uvs.empty() ? 0u : 1u;
  fc->num_lights = static_cast<uint32_t>(s.lights.size());
  fc->num_materials = static_cast<uint32_t>(s.materials.size());
  fc->num_textures = static_cast<uint32_t>(s.textures.size());
  fc->occupancy_bytes = occupancy_.size();
  fc->cell_records = cell_records_ea_;
  fc->subgrids = subgrids_ea_;
  fc->leaf_records = leaf_records_ea_;
  fc->bundles = bundles_ea_;
  fc->shading = shading_ea_;
  fc->materials = materials_ea_;
  fc->lights = lights_ea_;
  fc->occupancy = occupancy_ea_;
}

}  // namespace rs::sim
