// OctoMap side of scripts/octomap-compare: inserts PLY scans (binary little-endian, float x y z,
// header line "comment origin X Y Z") with OcTree::insertPointCloud(cloud, origin, maxrange,
// lazy_eval = false, discretize = false), using the same log-odds as glasshouse-roimap.
//
//   compare time  <resolution> <max_range|-1> <runs> A.ply [B.ply ...]   -> one JSON line
//   compare dump  <resolution> <max_range|-1> OUT.txt A.ply [B.ply ...]  -> "kx ky kz bits" lines
//
// Keys in the dump are OctoMap keys minus 32768 (so they equal glasshouse-roimap keys); bits is
// the occupancy log-odds as the hex of its IEEE float bits. Pruned leaves are expanded.
#include <octomap/octomap.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

using octomap::point3d;

struct Scan {
  point3d origin;
  octomap::Pointcloud cloud;
};

// Same log-odds values as MapConfig::default() (the probabilities OctoMap's setters take would
// round differently).
struct Tree : public octomap::OcTree {
  explicit Tree(double res) : octomap::OcTree(res) {
    prob_hit_log = 0.8473f;
    prob_miss_log = -0.4055f;
    clamping_thres_min = -2.0f;
    clamping_thres_max = 3.5110f;
    occ_prob_thres_log = 0.0f;
  }
};

static bool read_ply(const std::string& path, Scan& scan) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return false;
  std::string line;
  size_t count = 0;
  bool binary = false, have_origin = false;
  int props = 0;
  while (std::getline(in, line)) {
    std::istringstream ls(line);
    std::string w;
    ls >> w;
    if (w == "format") {
      std::string f;
      ls >> f;
      binary = f == "binary_little_endian";
    } else if (w == "comment") {
      std::string what;
      ls >> what;
      if (what == "origin") {
        float x, y, z;
        ls >> x >> y >> z;
        scan.origin = point3d(x, y, z);
        have_origin = true;
      }
    } else if (w == "element") {
      std::string name;
      ls >> name >> count;
    } else if (w == "property") {
      props++;
    } else if (w == "end_header") {
      break;
    }
  }
  if (!binary || props != 3 || !have_origin) {
    std::cerr << path << ": expected binary_little_endian float x y z with comment origin\n";
    return false;
  }
  std::vector<float> xyz(count * 3);
  in.read(reinterpret_cast<char*>(xyz.data()), static_cast<std::streamsize>(xyz.size() * 4));
  if (!in) return false;
  scan.cloud.reserve(count);
  for (size_t i = 0; i < count; i++) scan.cloud.push_back(xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]);
  return true;
}

static size_t expanded_leaves(const Tree& t) {
  size_t n = 0;
  for (auto it = t.begin_leafs(), end = t.end_leafs(); it != end; ++it) {
    size_t side = static_cast<size_t>(1) << (t.getTreeDepth() - it.getDepth());
    n += side * side * side;
  }
  return n;
}

int main(int argc, char** argv) {
  if (argc < 6) {
    std::cerr << "usage: compare time <res> <max_range|-1> <runs> A.ply...\n"
                 "       compare dump <res> <max_range|-1> OUT.txt A.ply...\n";
    return 2;
  }
  std::string mode = argv[1];
  double res = std::stod(argv[2]);
  double max_range = std::stod(argv[3]);
  std::vector<Scan> scans;
  for (int i = 5; i < argc; i++) {
    Scan s;
    if (!read_ply(argv[i], s)) {
      std::cerr << "cannot read " << argv[i] << "\n";
      return 1;
    }
    scans.push_back(std::move(s));
  }
  if (mode == "time") {
    int runs = std::stoi(argv[4]);
    std::vector<double> ms;
    size_t known = 0, memory = 0;
    for (int r = 0; r < runs; r++) {
      Tree tree(res);
      for (const Scan& s : scans) {
        auto t0 = std::chrono::steady_clock::now();
        tree.insertPointCloud(s.cloud, s.origin, max_range, false, false);
        auto t1 = std::chrono::steady_clock::now();
        ms.push_back(std::chrono::duration<double, std::milli>(t1 - t0).count());
      }
      known = expanded_leaves(tree);
      memory = tree.memoryUsage();
    }
    std::sort(ms.begin(), ms.end());
    std::printf(
        "{\"median_ms\": %.3f, \"min_ms\": %.3f, \"max_ms\": %.3f, \"known_voxels\": %zu, "
        "\"memory_bytes\": %zu}\n",
        ms[ms.size() / 2], ms.front(), ms.back(), known, memory);
    return 0;
  }
  if (mode == "dump") {
    Tree tree(res);
    for (const Scan& s : scans) tree.insertPointCloud(s.cloud, s.origin, max_range, false, false);
    std::FILE* out = std::fopen(argv[4], "w");
    if (!out) return 1;
    const int offset = 32768;
    for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
      octomap::OcTreeKey k = it.getIndexKey();
      int side = 1 << (tree.getTreeDepth() - it.getDepth());
      float v = it->getLogOdds();
      uint32_t bits;
      std::memcpy(&bits, &v, 4);
      for (int dx = 0; dx < side; dx++)
        for (int dy = 0; dy < side; dy++)
          for (int dz = 0; dz < side; dz++)
            std::fprintf(out, "%d %d %d %08x\n", int(k[0]) + dx - offset, int(k[1]) + dy - offset,
                         int(k[2]) + dz - offset, bits);
    }
    std::fclose(out);
    return 0;
  }
  std::cerr << "unknown mode " << mode << "\n";
  return 2;
}
