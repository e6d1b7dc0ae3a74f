package com.tbp.agent;

import java.io.File;
import java.io.FileOutputStream;
import java.io.IOException;
import java.nio.ByteBuffer;
import java.nio.channels.FileChannel;
import java.util.regex.Matcher;
import java.util.regex.Pattern;

/**
 * The agent's image folder, {@value #PHONE_FOLDER} on the phone: the only place it writes to and
 * deletes from. Images are named IMG_nnnnn.jpg, numbered on from the highest already there, and
 * written under a hidden temporary name first, so a file with the final name is always complete
 * and an image not yet pulled is never overwritten.
 */
public final class ImageStore {

    public static final String PHONE_FOLDER = "/sdcard/DCIM/tbp";
    /** Free space kept beyond an image before the agent answers STORAGE_FULL. */
    public static final long RESERVE_BYTES = 32L * 1024 * 1024;

    private static final Pattern IMAGE = Pattern.compile("IMG_(\\d{5,9})\\.jpg");
    private static final String PART_PREFIX = ".part-";

    /** Usable bytes in the folder's file system (a test or the simulator may stand in for the disk). */
    public interface FreeSpace {
        long usableBytes(File folder);
    }

    public static final FreeSpace DISK = new FreeSpace() {
        @Override
        public long usableBytes(File folder) {
            return folder.getUsableSpace();
        }
    };

    /** A written image: where the host finds it and its size. */
    public static final class Stored {
        public final String path;
        public final long size;

        Stored(String path, long size) {
            this.path = path;
            this.size = size;
        }
    }

    private final File folder;
    private final FreeSpace freeSpace;
    private long next;

    /**
     * @param folder where {@value #PHONE_FOLDER} is on this system (itself on a phone; a host folder
     *               under the simulator)
     */
    public ImageStore(File folder, FreeSpace freeSpace) {
        this.folder = folder;
        this.freeSpace = freeSpace;
    }

    /** Creates the folder, removes temporary files a killed agent left, finds the next number. */
    public void open() throws IOException {
        if (!folder.isDirectory() && !folder.mkdirs()) {
            throw new IOException("cannot create " + folder);
        }
        File[] files = folder.listFiles();
        if (files == null) {
            throw new IOException("cannot list " + folder);
        }
        long highest = -1;
        for (File file : files) {
            if (file.getName().startsWith(PART_PREFIX)) {
                if (!file.delete()) {
                    throw new IOException("cannot remove the partial image " + file);
                }
                continue;
            }
            Matcher m = IMAGE.matcher(file.getName());
            if (m.matches()) {
                highest = Math.max(highest, Long.parseLong(m.group(1)));
            }
        }
        next = highest + 1;
    }

    /** Writes one JPEG as the next image. */
    public Stored write(ByteBuffer jpeg) throws AgentError {
        long size = jpeg.remaining();
        long free = freeSpace.usableBytes(folder);
        if (free < size + RESERVE_BYTES) {
            throw new AgentError(ErrorCode.STORAGE_FULL, PHONE_FOLDER + ": " + free + " bytes free, a " + size
                    + "-byte image and the " + RESERVE_BYTES + "-byte reserve need more");
        }
        String name = String.format("IMG_%05d.jpg", next);
        File target = new File(folder, name);
        while (target.exists()) {  // put there by someone else since open(): never overwrite
            next++;
            name = String.format("IMG_%05d.jpg", next);
            target = new File(folder, name);
        }
        File part = new File(folder, PART_PREFIX + name);
        try {
            try (FileOutputStream out = new FileOutputStream(part); FileChannel channel = out.getChannel()) {
                while (jpeg.hasRemaining()) {
                    channel.write(jpeg);
                }
                channel.force(false);
            }
            if (!part.renameTo(target)) {
                throw new IOException("cannot rename " + part.getName() + " to " + name);
            }
        } catch (IOException e) {
            part.delete();
            long left = freeSpace.usableBytes(folder);
            ErrorCode code = left < size + RESERVE_BYTES ? ErrorCode.STORAGE_FULL : ErrorCode.CAPTURE_FAILED;
            throw new AgentError(code, "writing " + PHONE_FOLDER + "/" + name + ": " + e.getMessage());
        }
        next++;
        return new Stored(PHONE_FOLDER + "/" + name, size);
    }

    /** Removes an image the host has pulled: only a plain file name directly in the folder. */
    public void delete(String path) throws AgentError {
        String prefix = PHONE_FOLDER + "/";
        String name = path.startsWith(prefix) ? path.substring(prefix.length()) : null;
        if (name == null || name.isEmpty() || name.equals(".") || name.equals("..") || name.indexOf('/') >= 0
                || name.indexOf('\0') >= 0) {
            throw new AgentError(ErrorCode.BAD_REQUEST, "delete path " + Json.excerpt(path) + " is not a file in "
                    + PHONE_FOLDER);
        }
        File file = new File(folder, name);
        if (!file.isFile()) {
            throw new AgentError(ErrorCode.NOT_FOUND, path + " does not exist");
        }
        if (!file.delete()) {
            throw new AgentError(ErrorCode.CAMERA_ERROR, "cannot delete " + path);
        }
    }
}
